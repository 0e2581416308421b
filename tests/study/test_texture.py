"""The texture study: the --quick run end to end, determinism, resuming, validation."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from smdinspect.cli import main
from smdinspect.errors import InputError
from smdinspect.study import (
    METRICS,
    StudyCell,
    TextureStudyConfig,
    load_operator_table,
    run_cell,
    run_texture_study,
)
from smdinspect.synth import TEST_SEEDS

from .._procs import alive, children

SEED = TEST_SEEDS[14]
# a study of 4 cells and 2 operators: seconds, for the resume tests
TINY = dict(scenes=("cone", "steps"), textures=("band",), contrasts=(0.02, 0.2),
            freqs_cyc_px=(0.1,), read_noises=(0.005,), operators=("sml", "gder"),
            fits=("power",), size_px=48, n_frames=10, seed=SEED)


# the --quick grid with six operators of four families (all 25 take ~45 s on 2 cores: a
# benchmark, not a test)
QUICK_OPS = ("sml", "lape", "gder", "ten", "glva", "wavs")


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("study") / "quick"
    t0 = time.perf_counter()
    assert main(["-q", "study", "texture", "--quick", "--seed", str(SEED),
                 "--operators", ",".join(QUICK_OPS), "--out", str(out)]) == 0
    return out, time.perf_counter() - t0


def _rows(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_quick_outputs(quick, capsys):
    out, seconds = quick
    # its time is a benchmark figure (README), not asserted: it depends on the machine
    print(f"quick texture study: {seconds:.0f} s")
    cfg = TextureStudyConfig.quick(seed=SEED, operators=QUICK_OPS)
    names = {p.name for p in out.iterdir()}
    assert {"texture_study.csv", "texture_study.json", "texture_study.png", "texture_study.md",
            "texture_study_ranking.csv", "texture_study_ranking.png", "operator_table.json",
            "cells"} <= names
    rows = _rows(out / "texture_study.csv")
    assert len(rows) == len(cfg.cells()) * len(QUICK_OPS) * 2
    assert {r["operator"] for r in rows} == set(QUICK_OPS)
    assert {r["fit"] for r in rows} == {"power", "gauss3"}
    assert {r["scene"] for r in rows} == {"cone", "slanted_plane", "steps"}
    for r in rows:
        assert 0.0 <= float(r["coverage"]) <= 1.0
        assert 0.0 <= float(r["good_share"]) <= float(r["coverage"]) + 1e-9
        assert float(r["ms_per_frame"]) > 0
        if float(r["coverage"]) > 0:
            assert float(r["rmse_steps"]) >= 0 and r["bias_steps"] != ""
        else:
            assert r["rmse_steps"] == r["bias_steps"] == ""
    doc = json.loads((out / "texture_study.json").read_text())
    assert doc["settings"]["seed"] == SEED and doc["settings"]["size_px"] == 64
    ranking = doc["analysis"]["ranking"]["power"]
    assert [r["rank"] for r in ranking] == list(range(1, len(QUICK_OPS) + 1))
    assert all(a["score"] >= b["score"] for a, b in zip(ranking, ranking[1:]))
    for png in ("texture_study.png", "texture_study_ranking.png"):
        img = cv2.imread(str(out / png))
        assert img is not None and img.shape[0] > 300 and img.shape[1] > 400
    text = (out / "texture_study.md").read_text()
    for section in ("## Ranking", "## Which operator wins where",
                    "## Where no operator can", "## Contrast below which coverage",
                    "## Peak fits", "--operator auto"):
        assert section in text
    table = load_operator_table(out / "operator_table.json")
    assert len(table.keys) == len(cfg.cells()) and table.operators == QUICK_OPS


def test_quick_physics(quick):
    """Known ground truth: strong texture is measured, no texture is masked."""
    out, _ = quick
    rows = [r for r in _rows(out / "texture_study.csv") if r["fit"] == "power"]

    def best(sel):
        by_op = {}
        for r in sel:
            by_op.setdefault(r["operator"], []).append(float(r["good_share"]))
        return max(np.mean(v) for v in by_op.values())

    easy = [r for r in rows if r["texture"] == "band" and r["contrast"] == "0.2"
            and r["read_noise"] == "0.002" and r["freq_cyc_px"] == "0.15"]
    assert best(easy) > 0.7  # right and reliable on most of the pixels
    hard = [r for r in rows if r["contrast"] == "0.01" and r["read_noise"] == "0.02"]
    # no operator recovers these; the confidence must say so (little is claimed)
    assert best(hard) < 0.1
    assert np.mean([float(r["coverage"]) for r in hard]) < 0.05
    # the errors of what is claimed stay small where the texture is strong
    wrong = [float(r["wrong_share"]) for r in easy if r["wrong_share"]]
    assert np.median(wrong) < 0.05


def test_rerun_reuses_every_cell(quick, tmp_path):
    out, _ = quick
    study = run_texture_study(out, TextureStudyConfig.quick(seed=SEED, operators=QUICK_OPS),
                              write=False)
    assert study.computed == 0 and study.reused == 72


def test_cell_is_deterministic():
    cfg = TextureStudyConfig(**TINY)
    cell = StudyCell("steps", "band", 0.2, 0.1, 0.005)
    a, b = run_cell(cell, cfg), run_cell(cell, cfg)
    strip = [{k: v for k, v in r.items() if k != "ms_per_frame"} for r in a["rows"]]
    assert strip == [{k: v for k, v in r.items() if k != "ms_per_frame"} for r in b["rows"]]
    assert a["features"] == b["features"]
    other = run_cell(cell, TextureStudyConfig(**{**TINY, "seed": SEED + 1}))
    assert other["features"] != a["features"]


def test_finished_cells_are_not_recomputed(tmp_path):
    cfg = TextureStudyConfig(**TINY)
    first = run_texture_study(tmp_path, cfg, write=False)
    assert first.computed == 4 and first.reused == 0
    cells = sorted((tmp_path / "cells").glob("*.json"))
    assert len(cells) == 4
    # mark one stored cell: a rerun must read it, not recompute it
    doc = json.loads(cells[0].read_text())
    doc["rows"][0]["score"] = -7.0
    cells[0].write_text(json.dumps(doc))
    # a damaged cell and a cell of other settings are recomputed
    cells[1].write_text("{ not json")
    doc2 = json.loads(cells[2].read_text())
    doc2["fingerprint"] = "0" * 16
    cells[2].write_text(json.dumps(doc2))
    calls = []
    again = run_texture_study(tmp_path, cfg, progress=lambda d, t: calls.append((d, t)),
                              write=False)
    assert again.computed == 2 and again.reused == 2
    assert calls[0] == (2, 4) and calls[-1] == (4, 4)  # the bar starts at the work done
    scores = [r["score"] for c in again.cells for r in c["rows"]]
    assert -7.0 in scores
    assert json.loads(cells[1].read_text())["key"] == cells[1].stem


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_killed_run_resumes(tmp_path):
    """SIGKILL mid-run: the worker processes die too, the stored cells are whole, a rerun
    computes only the rest and gives the same table as an uninterrupted run."""
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "smdinspect", "-q", "study", "texture", "--quick",
           "--operators", "sml,gder", "--seed", str(SEED), "--workers", "2"]
    proc = subprocess.Popen(cmd + ["--out", str(out)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list((out / "cells").glob("[!.]*.json"))) < 5:
        time.sleep(0.05)
    workers = children(proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    # the worker processes die with the study instead of living on as orphans
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(alive(w) for w in workers):
        time.sleep(0.05)
    assert workers and not any(alive(w) for w in workers)
    stored = list((out / "cells").glob("[!.]*.json"))
    assert 5 <= len(stored) < 72
    for p in stored:
        assert json.loads(p.read_text())["key"] == p.stem  # no half-written cell
    r = subprocess.run(cmd + ["--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    reused = int(r.stdout.split(" reused")[0].rsplit(", ", 1)[1])
    assert reused >= len(stored)
    fresh = tmp_path / "fresh"
    r2 = subprocess.run(cmd + ["--out", str(fresh)], capture_output=True, text=True, timeout=120)
    assert r2.returncode == 0, r2.stderr

    def table(path):
        return [{k: v for k, v in row.items() if k != "ms_per_frame"}
                for row in _rows(path / "texture_study.csv")]

    assert table(out) == table(fresh)


def test_config_errors():
    with pytest.raises(InputError, match="operators must name some of"):
        TextureStudyConfig(operators=("sml", "nope"))
    with pytest.raises(InputError, match=r"contrasts must be a non-empty list of numbers in \[0, 1\]"):
        TextureStudyConfig(contrasts=(0.1, 2.0))
    with pytest.raises(InputError, match="window_px must be odd"):
        TextureStudyConfig(window_px=8)
    with pytest.raises(InputError, match="scenes must name some of cone"):
        TextureStudyConfig(scenes=("bore",))
    assert set(METRICS) >= {"rmse_steps", "bias_steps", "coverage", "wrong_share", "ms_per_frame"}


def test_cli_bad_operator(tmp_path, capsys):
    assert main(["study", "texture", "--quick", "--operators", "sml,xyz",
                 "--out", str(tmp_path / "o")]) == 2
    assert "operators must name some of" in capsys.readouterr().err
