"""``smdinspect batch``: local pool vs Dask, kill + resume, bad stacks, crashes, exit codes.

Real components only: synthetic boards rendered by ``smdinspect simulate board``, the
real pipeline (``smdinspect.pipeline.inspect_stack``), a real process pool, a real Dask
``LocalCluster`` on 127.0.0.1, the CLI in a subprocess killed with SIGKILL. The boards
are small (300 x 300 px at 0.04 mm/px, 23 frames) and rendered once per module.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from smdinspect.batch import (
    DONE_MARKER,
    SUMMARY_COLUMNS,
    BoardResult,
    BoardStatus,
    discover_stacks,
    read_done_marker,
    run_batch,
    stack_input_sha256,
)
from smdinspect.errors import InputError

REPO = Path(__file__).resolve().parents[1]
BOARD = REPO / "references" / "demo_board.json"
PY = sys.executable
N_JOINTS = 18  # joints of references/demo_board.json

# name -> (seed, defects, offset_mm, rotate_deg); two folders to exercise recursion.
BOARDS = {
    "lineA/board0": (0, "", "0.3,-0.2", "2"),
    "lineA/board1": (1, "R1.1:missing", "-0.2,0.3", "-1.5"),
    "lineB/board2": (2, "C2.1:insufficient", "0.1,0.1", "1"),
    "lineB/board3": (3, "U1.4:bridge", "-0.3,-0.1", "-2.5"),
}


def _simulate(out: Path, seed: int, defects: str, offset: str, rot: str) -> list[str]:
    cmd = [PY, "-m", "smdinspect", "-q", "simulate", "board", "--board", str(BOARD),
           "--seed", str(seed), "--size", "300", "--pixel-size-mm", "0.04",
           "--step-mm", "0.1", f"--offset-mm={offset}", f"--rotate-deg={rot}", "--out", str(out)]
    return cmd + (["--defects", defects] if defects else [])


@pytest.fixture(scope="module")
def stacks(tmp_path_factory) -> Path:
    """Four synthetic demo boards (rendered two at a time)."""
    root = tmp_path_factory.mktemp("batch") / "stacks"
    procs = []
    for name, (seed, defects, offset, rot) in BOARDS.items():
        procs.append(subprocess.Popen(_simulate(root / name, seed, defects, offset, rot),
                                      cwd=REPO, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True))
        if len(procs) % 2 == 0:
            for p in procs[-2:]:
                assert p.wait(120) == 0, p.stderr.read()
    return root


@pytest.fixture(scope="module")
def pool_run(stacks, tmp_path_factory):
    """The reference: the four boards through the local process pool (2 workers)."""
    out = tmp_path_factory.mktemp("pool") / "reports"
    return run_batch(stacks, BOARD, out, workers=2)


def _report(path: Path, *, drop: tuple[str, ...] = ()) -> dict:
    """report.json without its timing fields (and the keys in ``drop``)."""
    doc = json.loads(path.read_text())
    skip = ("created", "seconds", "timestamp", "finished_utc") + drop

    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k not in skip}
        if isinstance(o, list):
            return [strip(v) for v in o]
        return o

    return strip(doc)


def _leftovers(out: Path) -> list[Path]:
    return [p for p in out.rglob(".smdinspect-*") if p.is_dir()]


def _summary_rows(out: Path) -> dict[str, dict]:
    with open(out / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == SUMMARY_COLUMNS
    return {r["stack"]: r for r in rows}


# -- the local pool ------------------------------------------------------------------


def test_pool_batch_reports_every_board(pool_run, stacks):
    res = pool_run
    assert [b.stack for b in res.boards] == sorted(BOARDS)
    assert res.executor == "process-pool(2 workers)"
    for b in res.boards:
        out = Path(b.out_dir)
        assert out == res.out_dir.resolve() / b.stack
        rep = json.loads((out / "report.json").read_text())
        # the summary row is what the pipeline reported for that board
        assert b.status is not BoardStatus.ERROR, b.reason
        assert b.exit_code == rep["exit_code"]
        assert b.status.value == ("defects" if rep["exit_code"] else "ok")
        assert (b.joints, b.defects, b.unreliable) == (
            N_JOINTS, rep["summary"]["defects"], rep["summary"]["unreliable"])
        assert b.skipped is False and b.seconds > 0
        assert rep["measurement"]["source"] == str((stacks / b.stack).resolve())
        for f in ("report.json", "junit.xml", "joints.csv", "report.html", DONE_MARKER):
            assert (out / f).is_file(), f
        marker = json.loads((out / DONE_MARKER).read_text())
        assert marker["input_sha256"] == b.input_sha256 and len(b.input_sha256) == 64
        assert set(marker["outputs"]) >= {"report.json", "junit.xml", "joints.csv"}
        assert read_done_marker(out, input_sha256=b.input_sha256) is not None
    # exit code: 2 if an error, else 1 if defects, else 0
    want = 1 if any(b.status is BoardStatus.DEFECTS for b in res.boards) else 0
    assert res.exit_code == want
    assert _leftovers(res.out_dir) == []

    rows = _summary_rows(res.out_dir)
    assert set(rows) == set(BOARDS)
    for b in res.boards:
        r = rows[b.stack]
        assert (r["status"], int(r["exit_code"]), int(r["joints"]), int(r["defects"]),
                r["skipped"]) == (b.status.value, b.exit_code, b.joints, b.defects, "false")
    summary = json.loads((res.out_dir / "summary.json").read_text())
    assert summary["exit_code"] == res.exit_code
    assert summary["boards_total"] == 4 and len(summary["boards"]) == 4
    assert summary["counts"]["error"] == 0 and summary["counts"]["skipped"] == 0

    # one merged JUnit: a testsuite per board holding that board's cases
    root = ET.parse(res.out_dir / "junit.xml").getroot()
    suites = root.findall("testsuite")
    assert [s.get("name") for s in suites] == sorted(BOARDS)
    assert int(root.get("tests")) == 4 * N_JOINTS
    for s in suites:
        b = res.board(s.get("name"))
        cases = s.findall("testcase")
        assert len(cases) == int(s.get("tests")) == N_JOINTS
        assert all(c.get("classname").startswith(b.stack + ".") for c in cases)
        failed = sorted(c.get("name") for c in cases if c.find("failure") is not None)
        own = ET.parse(Path(b.out_dir) / "junit.xml").getroot()
        assert failed == sorted(c.get("name") for c in own.iter("testcase")
                                if c.find("failure") is not None)
        assert len(failed) == b.defects


def test_batch_report_is_the_pipeline_report(pool_run, stacks, tmp_path):
    """A board's batch report (one thread per board) equals a direct ``inspect_stack``
    call on two threads: the report does not depend on the thread count."""
    from smdinspect._batch._job import limit_native_threads
    from smdinspect.pipeline import inspect_stack, inspection_focus_config
    from smdinspect.stack import FocalStack

    name = "lineB/board3"
    limit_native_threads(2)
    cfg = dataclasses.replace(inspection_focus_config(), workers=2)
    res = inspect_stack(FocalStack.open(stacks / name), BOARD, tmp_path, focus_config=cfg)
    b = pool_run.board(name)
    assert (b.exit_code, b.defects, b.unreliable) == (res.exit_code, len(res.defects),
                                                     len(res.unreliable))
    assert _report(tmp_path / "report.json") == _report(Path(b.out_dir) / "report.json")


# -- Dask ----------------------------------------------------------------------------


def test_dask_local_cluster_gives_the_pool_reports(pool_run, stacks, tmp_path):
    from distributed import LocalCluster

    out = tmp_path / "reports"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None,  # and its HTTP endpoint on a free port:
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        res = run_batch(stacks, BOARD, out, scheduler=cluster.scheduler_address)
    assert res.executor.startswith("dask(tcp://127.0.0.1:")
    assert res.exit_code == pool_run.exit_code
    for b, ref in zip(res.boards, pool_run.boards):
        assert (b.stack, b.status, b.exit_code, b.joints, b.defects, b.unreliable, b.reason,
                b.input_sha256) == (ref.stack, ref.status, ref.exit_code, ref.joints,
                                    ref.defects, ref.unreliable, ref.reason, ref.input_sha256)
        assert _report(Path(b.out_dir) / "report.json") == _report(
            Path(ref.out_dir) / "report.json")
        assert (Path(b.out_dir) / "joints.csv").read_bytes() == (
            Path(ref.out_dir) / "joints.csv").read_bytes()
    rows, ref_rows = _summary_rows(out), _summary_rows(pool_run.out_dir)
    for name in BOARDS:
        for k in ("status", "exit_code", "joints", "defects", "unreliable", "reason", "skipped"):
            assert rows[name][k] == ref_rows[name][k]
    assert _leftovers(out) == []


# -- kill and resume -----------------------------------------------------------------


def _children(pid: int) -> list[int]:
    kids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                stat = (p / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(p.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and SIGKILL")
def test_killed_batch_rerun_finishes_the_rest(pool_run, stacks, tmp_path):
    out = tmp_path / "reports"
    cmd = [PY, "-m", "smdinspect", "-q", "batch", str(stacks), "--board", str(BOARD),
           "--out", str(out), "--workers", "2"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not list(out.rglob(DONE_MARKER)):
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() < deadline, "no board finished within 120 s"
        time.sleep(0.02)
    kids = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    proc.stderr.close()
    done_before = {p.parent.relative_to(out).as_posix(): p.stat().st_mtime_ns
                   for p in out.rglob(DONE_MARKER)}
    assert 1 <= len(done_before) < 4, "the kill must land mid-batch"
    assert not (out / "summary.csv").exists()
    # the pool's worker processes die with the batch (no orphan keeps writing reports)
    t = time.monotonic()
    while any(_alive(k) for k in kids) and time.monotonic() - t < 10:
        time.sleep(0.05)
    assert kids and not any(_alive(k) for k in kids)

    rerun = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=180)
    assert rerun.returncode == pool_run.exit_code, rerun.stderr
    rows = _summary_rows(out)
    assert set(rows) == set(BOARDS)
    for name, row in rows.items():
        board_dir = out / name
        assert row["skipped"] == ("true" if name in done_before else "false")
        if name in done_before:  # not redone: the marker is the one of the killed run
            assert (board_dir / DONE_MARKER).stat().st_mtime_ns == done_before[name]
        ref = pool_run.board(name)
        assert row["status"] == ref.status.value and int(row["exit_code"]) == ref.exit_code
        # every board once, complete and identical to an uninterrupted run
        assert _report(board_dir / "report.json") == _report(Path(ref.out_dir) / "report.json")
        marker = json.loads((board_dir / DONE_MARKER).read_text())
        assert marker["input_sha256"] == ref.input_sha256  # --workers is not an input
        assert read_done_marker(board_dir, input_sha256=ref.input_sha256) is not None
    assert sorted(p.parent.relative_to(out).as_posix() for p in out.rglob("report.json")) \
        == sorted(BOARDS)
    assert _leftovers(out) == []

    # a third run has nothing left to do
    t = time.perf_counter()
    again = run_batch(stacks, BOARD, out, workers=2)
    assert all(b.skipped for b in again.boards)
    assert again.exit_code == pool_run.exit_code
    assert time.perf_counter() - t < 20


# -- bad boards, crashes -------------------------------------------------------------


def test_bad_stacks_fail_only_their_board(pool_run, stacks, tmp_path):
    """Through the CLI with --dask-local: corrupt, broken, missing, not located."""
    from smdinspect import cli
    from smdinspect.stack import StackWriter

    src = tmp_path / "stacks"
    shutil.copytree(stacks / "lineA/board0", src / "good")
    shutil.copytree(stacks / "lineA/board1", src / "truncated")
    frame = src / "truncated" / "frame_0010.png"
    frame.write_bytes(frame.read_bytes()[:500])
    shutil.copytree(stacks / "lineB/board2", src / "missing_frame")
    (src / "missing_frame" / "frame_0003.png").unlink()
    (src / "bad_json").mkdir()
    (src / "bad_json" / "stack.json").write_text('{"frames": [')
    # a flat textured plane: reconstructs fine, but there is no board to locate
    rng = np.random.default_rng(5)
    tex = (rng.random((160, 160)) * 255).astype(np.float32)
    w = StackWriter(src / "no_board", pixel_size_mm=0.04)
    import cv2
    for k in range(7):
        w.add_frame(cv2.GaussianBlur(tex, (0, 0), 0.6 + abs(k - 3)).astype(np.uint8), 0.1 * k)

    out = tmp_path / "reports"
    code = cli.main(["-q", "batch", str(src), "--board", str(BOARD), "--out", str(out),
                     "--dask-local", "2"])
    assert code == 2  # an error outranks the defects
    rows = _summary_rows(out)
    assert set(rows) == {"good", "truncated", "missing_frame", "bad_json", "no_board"}
    ref = pool_run.board("lineA/board0")
    assert rows["good"]["status"] == ref.status.value
    assert _report(out / "good" / "report.json", drop=("source",)) == _report(
        Path(ref.out_dir) / "report.json", drop=("source",))
    expect = {"truncated": (2, "frame_0010.png is truncated"),
              "missing_frame": (2, "frame_0003.png"),
              "bad_json": (2, "not valid JSON"),
              "no_board": (3, "not located")}
    for name, (exit_code, words) in expect.items():
        r = rows[name]
        assert (r["status"], int(r["exit_code"]), r["joints"]) == ("error", exit_code, ""), r
        assert words in r["reason"], r["reason"]
        err = json.loads((out / name / "error.json").read_text())
        assert err["exit_code"] == exit_code and words in err["reason"]
        assert not (out / name / DONE_MARKER).exists()
    # the not-located board keeps the pipeline's explanation next to error.json
    assert json.loads((out / "no_board" / "report.json").read_text())["status"] == "not_located"
    root = ET.parse(out / "junit.xml").getroot()
    errors = {s.get("name"): s.find("testcase/error") for s in root.findall("testsuite")}
    assert {n for n, e in errors.items() if e is not None} == set(expect)
    assert int(root.get("errors")) == 4
    summary = json.loads((out / "summary.json").read_text())
    assert summary["executor"] == "dask-local(2 workers)"
    assert summary["counts"]["error"] == 4 and summary["exit_code"] == 2
    assert _leftovers(out) == []

    # errored boards are retried on the next run, the good one is skipped
    (src / "bad_json" / "stack.json").unlink()
    shutil.rmtree(src / "bad_json")
    again = run_batch(src, BOARD, out, workers=1)
    assert again.board("good").skipped
    assert not again.board("truncated").skipped
    assert again.board("truncated").status is BoardStatus.ERROR


def crash_on_segv_stack(stack, board, out_dir, **kwargs):
    """``inspect_fn`` for the crash test: a real segfault of the worker process for the
    stack named ``segv``; every other stack goes through the real pipeline."""
    if stack.root.name == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    from smdinspect.pipeline import inspect_stack

    return inspect_stack(stack, board, out_dir, **kwargs)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGSEGV semantics")
def test_crashing_worker_fails_only_its_board(stacks, tmp_path):
    src = tmp_path / "stacks"
    shutil.copytree(stacks / "lineA/board0", src / "segv")
    for name in ("a_truncated", "z_truncated"):
        shutil.copytree(stacks / "lineA/board1", src / name)
        f = src / name / "frame_0004.png"
        f.write_bytes(f.read_bytes()[:300])
    (src / "bad_json").mkdir()
    (src / "bad_json" / "stack.json").write_text("[1, 2")
    res = run_batch(src, BOARD, tmp_path / "reports", workers=2,
                    inspect_fn="tests.test_batch:crash_on_segv_stack")
    assert res.exit_code == 2
    segv = res.board("segv")
    assert segv.status is BoardStatus.ERROR and "worker process died" in segv.reason
    assert json.loads((Path(segv.out_dir) / "error.json").read_text())["exit_code"] == 2
    # the boards that shared the pool with the crash get their own verdicts
    for name in ("a_truncated", "z_truncated"):
        assert "frame_0004.png is truncated" in res.board(name).reason
    assert "not valid JSON" in res.board("bad_json").reason
    assert _leftovers(tmp_path / "reports") == []


# -- the pieces, without the pipeline ------------------------------------------------


def _result(status: str) -> BoardResult:
    st = BoardStatus(status)
    code = {"ok": 0, "defects": 1, "error": 3}[status]
    return BoardResult(stack=status, status=st, exit_code=code,
                       joints=None, defects=None, unreliable=None, reason="", seconds=0.0,
                       skipped=False, out_dir="")


def test_batch_exit_code_precedence():
    from smdinspect._batch import batch_exit_code

    assert batch_exit_code([_result("ok"), _result("ok")]) == 0
    assert batch_exit_code([_result("ok"), _result("defects")]) == 1
    assert batch_exit_code([_result("defects"), _result("error"), _result("ok")]) == 2
    assert batch_exit_code([_result("error")]) == 2


def _fake_stack(path: Path) -> None:
    path.mkdir(parents=True)
    (path / "stack.json").write_text('{"frames": []}')


def test_discovery_rules(tmp_path):
    root = tmp_path / "stacks"
    for rel in ("a/s1", "a/b/s2", "s3", ".hidden/s4", "reports/x", "s3/inner"):
        _fake_stack(root / rel)
    (root / "empty").mkdir()
    (root / "loop").symlink_to(root, target_is_directory=True)  # cycle: visited once
    (root / "link").symlink_to(root / "a" / "b", target_is_directory=True)
    names = [n for n, _ in discover_stacks(root, exclude=(root / "reports",))]
    assert names == ["a/b/s2", "a/s1", "s3"]  # link → a/b is the same folder as a/b
    assert discover_stacks(root / "a" / "s1")[0][0] == "s1"  # a stack dir itself: one board
    with pytest.raises(InputError, match="stacks folder not found"):
        discover_stacks(tmp_path / "nope")


def test_fingerprint_tracks_content_not_mtime(stacks, tmp_path):
    src = tmp_path / "s"
    shutil.copytree(stacks / "lineA/board0", src)
    kw = dict(board_sha256="b" * 64, settings={"focus": {"window_px": 9}})
    base = stack_input_sha256(src, **kw)
    frame = src / "frame_0007.png"
    os.utime(frame, ns=(1, 1))
    assert stack_input_sha256(src, **kw) == base  # touching is not changing
    data = bytearray(frame.read_bytes())
    data[100] ^= 0xFF
    frame.write_bytes(bytes(data))
    changed = stack_input_sha256(src, **kw)
    assert changed != base
    assert stack_input_sha256(src, board_sha256="c" * 64, settings=kw["settings"]) != changed
    assert stack_input_sha256(src, board_sha256=kw["board_sha256"],
                              settings={"focus": {"window_px": 11}}) != changed


def test_done_marker_rejects_other_inputs_and_tampered_reports(pool_run, tmp_path):
    ref = pool_run.board("lineB/board3")
    copy = tmp_path / "board3"
    shutil.copytree(ref.out_dir, copy)
    done = read_done_marker(copy, input_sha256=ref.input_sha256)
    assert done is not None and done.skipped
    assert (done.status, done.joints, done.defects) == (ref.status, ref.joints, ref.defects)
    assert read_done_marker(copy, input_sha256="0" * 64) is None
    with open(copy / "report.json", "ab") as fh:
        fh.write(b" ")
    assert read_done_marker(copy, input_sha256=ref.input_sha256) is None


def test_bad_arguments_fail_before_any_work(stacks, tmp_path):
    with pytest.raises(InputError, match="not both"):
        run_batch(stacks, BOARD, tmp_path / "o", scheduler="tcp://127.0.0.1:1", dask_workers=1)
    with pytest.raises(InputError, match="workers must be an integer >= 1; got 0"):
        run_batch(stacks, BOARD, tmp_path / "o", workers=0)
    with pytest.raises(InputError, match="must not be"):
        run_batch(stacks / "lineA", BOARD, stacks.parent, workers=1)
    with pytest.raises(InputError, match="inside the stack"):
        run_batch(stacks, BOARD, stacks / "lineA" / "board0" / "reports", workers=1)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no stack directories"):
        run_batch(tmp_path / "empty", BOARD, tmp_path / "o", workers=1)
    bad_board = tmp_path / "bad_board.json"
    bad_board.write_text('{"schema": "smdinspect-board"')
    with pytest.raises(InputError, match="bad_board.json"):
        run_batch(stacks, bad_board, tmp_path / "o", workers=1)
    assert not (tmp_path / "o").exists()  # nothing was written


def test_one_batch_per_report_folder(stacks, tmp_path):
    from smdinspect._batch._run import _locked

    out = tmp_path / "reports"
    out.mkdir()
    with _locked(out):
        with pytest.raises(InputError, match="another smdinspect batch is writing"):
            run_batch(stacks, BOARD, out, workers=1)


def test_clean_leftovers_removes_only_temporary_folders(tmp_path):
    from smdinspect._batch import clean_leftovers

    board = tmp_path / "line" / "board"
    board.mkdir(parents=True)
    (board / DONE_MARKER).write_text("{}")
    temp = [tmp_path / "line" / ".smdinspect-partial-board-x1",
            tmp_path / "line" / ".smdinspect-old-board-x2",
            board / ".smdinspect-partial-inner-x3"]
    for t in temp:
        t.mkdir()
        (t / "report.json").write_text("half")
    keep = tmp_path / "line" / ".other"
    keep.mkdir()
    assert sorted(clean_leftovers(tmp_path)) == sorted(temp)
    assert not any(t.exists() for t in temp)
    assert keep.is_dir() and (board / DONE_MARKER).is_file()
