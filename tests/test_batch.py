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

from ._procs import alive, children

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


class _Events:
    """A ``board_progress`` callback that records what it is told (thread-safe)."""

    def __init__(self):
        import threading

        self.lock = threading.Lock()
        self.events: list[tuple[str, str, int, int]] = []

    def __call__(self, stack, stage, done, total):
        with self.lock:
            self.events.append((stack, stage, done, total))

    def of(self, stack):
        return [e[1:] for e in self.events if e[0] == stack]


@pytest.fixture(scope="module")
def pool_events():
    return _Events()


@pytest.fixture(scope="module")
def pool_run(stacks, tmp_path_factory, pool_events):
    """The reference: the four boards through the local process pool (2 workers)."""
    out = tmp_path_factory.mktemp("pool") / "reports"
    return run_batch(stacks, BOARD, out, workers=2, board_progress=pool_events)


def _check_progress(events: _Events, names, *, skipped=()):
    """Every board moved frame by frame to its last frame, then was inspected, then
    ended exactly once (``done``, or ``skipped`` without any stage)."""
    for name in names:
        ev = events.of(name)
        end = [e for e in ev if e[0] in ("done", "skipped")]
        assert end == [("skipped" if name in skipped else "done", 1, 1)], ev
        if name in skipped:
            assert ev == end
            continue
        frames = [e for e in ev if e[0] == "reconstruct"]
        n = frames[0][2]
        assert n == 23 and frames[0][1] == 0  # the demo stacks have 23 frames
        assert [f[1] for f in frames] == sorted(f[1] for f in frames)
        assert frames[-1][1] == n  # (small boards: the in-between frames are throttled)
        assert ("inspect", 0, 1) in ev
        assert ev.index(("inspect", 0, 1)) > ev.index(frames[-1])


def test_board_progress_is_throttled_not_lost(monkeypatch):
    """Per-frame messages at most every 0.2 s, the first and last frame always; the
    ``inspect`` stage always; a failing sink never reaches the board."""
    from smdinspect._batch import _job

    clock = [100.0]
    monkeypatch.setattr(_job.time, "monotonic", lambda: clock[0])
    sent = []
    monkeypatch.setattr(_job, "_progress_sink", sent.append)
    job = _job.BoardJob(name="b", stack_dir="/x", out_dir="/y", board=None,
                        board_sha256="", settings={})
    report = _job._reporter(job)
    for i in range(11):
        report("reconstruct", i, 10)
        clock[0] += 0.0625  # 16 frames/s: every 4th frame gets through
    report("inspect", 0, 1)
    assert [m[2] for m in sent if m[1] == "reconstruct"] == [0, 4, 8, 10]
    assert sent[-1] == ("b", "inspect", 0, 1)

    def broken(msg):
        raise BrokenPipeError

    monkeypatch.setattr(_job, "_progress_sink", broken)
    _job._reporter(job)("inspect", 0, 1)  # no exception
    monkeypatch.setattr(_job, "_progress_sink", None)
    assert _job._reporter(job) is None


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


def test_pool_batch_progress_moves_within_each_board(pool_run, pool_events):
    _check_progress(pool_events, BOARDS)


def test_batch_progress_bar_shows_boards_stages_and_no_rate():
    from smdinspect._cli.batch import BatchProgress

    bar = BatchProgress(disable=True)
    bar.boards(0, 3)
    assert bar.position() == 0 and "0/3 boards done; starting workers" == bar.status()
    bar.board("b1", "reconstruct", 10, 20)
    bar.board("b2", "reconstruct", 0, 20)
    assert bar.position() == pytest.approx(0.5 * bar.RECONSTRUCT_SHARE)
    assert bar.status() == "0/3 boards done; b1: frame 10/20; b2: frame 0/20"
    bar.board("b1", "inspect", 0, 1)
    assert "b1: measuring + writing reports" in bar.status()
    bar.board("b1", "done", 1, 1)
    bar.boards(1, 3)
    bar.board("b1", "reconstruct", 20, 20)  # late message: ignored
    assert bar.position() == pytest.approx(1.0)
    bar.board("b3", "skipped", 1, 1)
    bar.boards(2, 3)
    assert bar.n_skip_fast == 1 and bar.position() == pytest.approx(2.0)
    bar.close()


def test_batch_progress_bar_draws(tmp_path):
    """A real tqdm bar into a file: the postfix moves, no "/s" rate appears."""
    from smdinspect._cli.batch import BatchProgress

    with open(tmp_path / "bar.txt", "w") as fh:
        bar = BatchProgress(file=fh)
        bar._open = lambda: None  # tqdm(disable=None) stays off on a non-TTY: force it
        from tqdm import tqdm

        bar.bar = tqdm(total=2, file=fh, bar_format=bar.BAR_FORMAT)
        bar.boards(0, 2)
        for done in (5, 10):
            bar._last_draw = 0.0  # no redraw throttling here
            bar.board("b1", "reconstruct", done, 10)
        bar.close()
    text = (tmp_path / "bar.txt").read_text()
    assert "| 0/2 boards done; b1: frame 5/10 [" in text and "b1: frame 10/10" in text
    assert "/s" not in text and "boards done; starting workers" in text
    assert " 18%|" in text and " 35%|" in text  # half of a board's reconstruct share (0.7) of 1 board in 2


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


def test_batch_page_and_spc_across_boards(pool_run):
    """The batch writes spc/ (SPC across its inspected boards, in stack order) and an
    index.html with every board's verdict linked to its report."""
    out = pool_run.out_dir
    assert pool_run.index_html == out / "index.html"
    page = pool_run.index_html.read_text()
    for name in BOARDS:
        assert f'href="{name}/report.html"' in page
    assert page.count("FAIL") == sum(b.status is BoardStatus.DEFECTS for b in pool_run.boards)
    assert 'href="spc/spc.html"' in page and 'href="spc/spc.csv"' in page
    spc = pool_run.spc
    assert [b.label for b in spc.boards] == sorted(BOARDS)
    with open(out / "spc" / "spc.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    joints = {r["key"] for r in rows if r["scope"] == "joint"}
    assert len(joints) == N_JOINTS and all(r["n_boards"] == "4" for r in rows)
    r = next(r for r in rows if r["key"] == "R2.1" and r["metric"] == "max_height_mm")
    heights = [json.loads((Path(b.out_dir) / "report.json").read_text())
               for b in pool_run.boards]
    h = [next(j for j in d["joints"] if j["id"] == "R2.1")["measured"]["max_height_mm"]
         for d in heights]
    assert float(r["mean"]) == pytest.approx(np.mean(h), rel=1e-4)
    assert (out / "spc" / r["chart_png"]).is_file()


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


def _pem_files(folder: Path, names=("ca", "scheduler", "worker", "client", "rogue")) -> dict:
    """A CA and certificates it signed (PEM; ``rogue`` is self-signed, not by the CA)."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    folder.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)

    def make(cn, issuer_key=None, issuer_name=None, ca=False):
        key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])
        cert = (x509.CertificateBuilder().subject_name(name)
                .issuer_name(issuer_name or name).public_key(key.public_key())
                .serial_number(x509.random_serial_number())
                .not_valid_before(now - datetime.timedelta(minutes=5))
                .not_valid_after(now + datetime.timedelta(days=1))
                .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
                .sign(issuer_key or key, hashes.SHA256()))
        return key, cert

    files = {}

    def write(tag, key, cert):
        (folder / f"{tag}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        (folder / f"{tag}.key").write_bytes(key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
        files[tag] = (folder / f"{tag}.pem", folder / f"{tag}.key")

    ca_key, ca_cert = make("smdinspect test CA", ca=True)
    write("ca", ca_key, ca_cert)
    for tag in names[1:]:
        if tag == "rogue":
            write(tag, *make("rogue"))
        else:
            write(tag, *make(tag, ca_key, ca_cert.subject))
    return files


@pytest.fixture
def tls_cluster(tmp_path):
    """A real TLS Dask cluster on 127.0.0.1: ``dask scheduler`` and ``dask worker``
    (2 single-threaded worker processes) started with CA-signed certificates."""
    pem = _pem_files(tmp_path / "pki")
    ca = str(pem["ca"][0])
    dask_cli = [PY, "-m", "dask"]  # the `dask` command of this environment
    sched_file = tmp_path / "scheduler.json"
    sched = subprocess.Popen(
        dask_cli + ["scheduler", "--host", "127.0.0.1", "--port", "0", "--protocol", "tls",
                    "--no-dashboard", "--scheduler-file", str(sched_file), "--tls-ca-file", ca,
                    "--tls-cert", str(pem["scheduler"][0]), "--tls-key", str(pem["scheduler"][1])],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [sched]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert sched.poll() is None and time.monotonic() < deadline, "no scheduler"
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        procs.append(subprocess.Popen(
            dask_cli + ["worker", address, "--nworkers", "2", "--nthreads", "1",
                        "--host", "127.0.0.1", "--no-dashboard",
                        "--local-directory", str(tmp_path / "worker-scratch"),
                        "--tls-ca-file", ca, "--tls-cert", str(pem["worker"][0]),
                        "--tls-key", str(pem["worker"][1])],
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        yield address, pem
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_dask_tls_cluster_gives_the_pool_reports(pool_run, stacks, tmp_path, tls_cluster):
    from smdinspect.batch import DaskTLS

    address, pem = tls_cluster
    assert address.startswith("tls://127.0.0.1:")
    ca = pem["ca"][0]
    events = _Events()
    out = tmp_path / "reports"
    res = run_batch(stacks, BOARD, out, scheduler=address, board_progress=events,
                    tls=DaskTLS(ca_file=ca, cert_file=pem["client"][0],
                                key_file=pem["client"][1]))
    assert res.executor == f"dask({address})"
    _check_progress(events, BOARDS)
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

    # the CLI reaches the same cluster with the same files (every board unchanged)
    from smdinspect import cli

    code = cli.main(["-q", "batch", str(stacks), "--board", str(BOARD), "--out", str(out),
                     "--scheduler", address, "--tls-ca-file", str(ca),
                     "--tls-cert", str(pem["client"][0]), "--tls-key", str(pem["client"][1])])
    assert code == pool_run.exit_code
    assert json.loads((out / "summary.json").read_text())["counts"]["skipped"] == len(BOARDS)

    # without a certificate the CA signed, nobody gets in
    from smdinspect._batch import dask_client

    with pytest.raises(InputError, match="uses TLS: give its CA file"):
        with dask_client(scheduler=address):
            pass
    rogue = DaskTLS(ca_file=ca, cert_file=pem["rogue"][0], key_file=pem["rogue"][1])
    with pytest.raises(InputError, match="cannot connect to the Dask scheduler"):
        with dask_client(scheduler=address, tls=rogue, connect_timeout_s=5):
            pass
    with pytest.raises(InputError, match="cannot connect"):
        with dask_client(scheduler=address.replace("tls://", "tcp://"), connect_timeout_s=5):
            pass
    with pytest.raises(InputError, match="not tls://"):
        with dask_client(scheduler=address.replace("tls://", "tcp://"),
                         tls=DaskTLS(ca_file=ca, cert_file=pem["client"][0],
                                     key_file=pem["client"][1])):
            pass
    with pytest.raises(InputError, match="TLS cert file not found"):
        DaskTLS(ca_file=ca, cert_file=tmp_path / "nope.pem")
    assert cli.main(["-q", "batch", str(stacks), "--board", str(BOARD), "--out",
                     str(tmp_path / "o2"), "--dask-local", "1", "--tls-ca-file", str(ca),
                     "--tls-cert", str(ca)]) == 2
    assert not (tmp_path / "o2").exists()


_LOCAL_CLUSTER_SCRIPT = """
import json, sys
from smdinspect._batch import dask_client

def main():
    with dask_client(local_workers=2) as (client, where):
        info = client.scheduler_info()
        print(json.dumps({
            "where": where,
            "address": client.scheduler.address,
            "workers": sorted(info["workers"]),
            "nannies": sorted(w["nanny"] for w in info["workers"].values()),
            "http": [info["services"]["dashboard"]]
                    + [w["services"]["dashboard"] for w in info["workers"].values()],
            "worker_dirs": sorted(client.run(lambda dask_worker: dask_worker.local_directory)
                                  .values()),
            "scheduler_dir": client.run_on_scheduler(
                lambda dask_scheduler: dask_scheduler.local_directory),
            "own_client_runs": client.run_on_scheduler(lambda: 41) + 1,
        }), flush=True)
        sys.stdin.readline()  # the test probes the cluster meanwhile

if __name__ == "__main__":
    main()
"""

_INTRUDER_SCRIPT = """
import json, os, socket, ssl, sys
from distributed import Client
from distributed.security import Security

def try_client(address, **kw):
    try:
        c = Client(address, timeout="4s", **kw)
    except Exception as exc:
        return "refused: " + type(exc).__name__
    try:
        return "RAN CODE ON THE SCHEDULER: pid %d" % c.run_on_scheduler(os.getpid)
    finally:
        c.close()

def raw_tls(address):
    host, port = address.split("://")[1].rsplit(":", 1)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
    try:
        with socket.create_connection((host, int(port)), timeout=4) as raw:
            with ctx.wrap_socket(raw) as s:
                s.sendall(b"\\x00" * 64)
                data = s.recv(64)
                return "refused: closed" if not data else "GOT DATA"
    except (ssl.SSLError, OSError) as exc:
        return "refused: " + type(exc).__name__

def main():
    info = json.loads(sys.argv[1])
    out = {}
    for kind in ("address", "workers", "nannies"):
        addrs = [info["address"]] if kind == "address" else info[kind]
        for a in addrs:
            out[f"{kind} {a} no security"] = try_client(a)
            out[f"{kind} {a} tcp"] = try_client(a.replace("tls://", "tcp://"))
            out[f"{kind} {a} other cert"] = try_client(a, security=Security.temporary())
            out[f"{kind} {a} raw tls"] = raw_tls(a)
    print(json.dumps(out))

if __name__ == "__main__":
    main()
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX modes")
def test_dask_local_cluster_is_private(tmp_path):
    """--dask-local: mutual TLS with a per-run certificate (another local process cannot
    connect to the scheduler, a worker or a nanny, let alone run code), scratch in a
    private 0700 folder (never $TMPDIR/dask-scratch-space), removed afterwards, and
    only the health check over HTTP."""
    import stat
    import urllib.error
    import urllib.request

    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    (tmp_path / "cluster.py").write_text(_LOCAL_CLUSTER_SCRIPT)
    (tmp_path / "intruder.py").write_text(_INTRUDER_SCRIPT)
    proc = subprocess.Popen([PY, str(tmp_path / "cluster.py")], cwd=REPO, env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline()
        assert line, "the local cluster did not start"
        info = json.loads(line)
        assert info["where"] == "dask-local(2 workers, tls)"
        assert info["own_client_runs"] == 42  # the batch's own client is let in
        assert info["address"].startswith("tls://127.0.0.1:")
        assert all(a.startswith("tls://127.0.0.1:") for a in info["workers"] + info["nannies"])
        # private scratch: one 0700 folder of ours in $TMPDIR, nothing else there
        top = list(tmpdir.iterdir())
        assert len(top) == 1 and top[0].name.startswith("smdinspect-dask-"), top
        assert stat.S_IMODE(top[0].stat().st_mode) == 0o700
        assert not (tmpdir / "dask-scratch-space").exists()
        for d in info["worker_dirs"] + [info["scheduler_dir"]]:
            assert Path(d).resolve().is_relative_to(top[0].resolve()), d
        # another process (no certificate of this run) is refused everywhere
        run = subprocess.run([PY, str(tmp_path / "intruder.py"), line], cwd=REPO,
                             capture_output=True, text=True, timeout=180)
        probes = json.loads(run.stdout.strip().splitlines()[-1])
        assert len(probes) == 4 * 5  # 4 ways into the scheduler, 2 workers, 2 nannies
        assert all(v.startswith("refused") for v in probes.values()), probes
        # HTTP: the health check only, no task/worker/log pages or metrics
        for port in info["http"]:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5) as r:
                assert r.read() == b"ok"
            for path in ("/info/main/workers.html", "/json/counts.json", "/metrics"):
                with pytest.raises(urllib.error.HTTPError, match="404"):
                    urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5)
        proc.stdin.write("\n")
        proc.stdin.flush()
        assert proc.wait(60) == 0
        assert list(tmpdir.iterdir()) == []  # the scratch folder went with the cluster
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# -- kill and resume -----------------------------------------------------------------


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and SIGKILL")
def test_killed_batch_rerun_finishes_the_rest(pool_run, stacks, tmp_path):
    out = tmp_path / "reports"
    cmd = [PY, "-m", "smdinspect", "-q", "batch", str(stacks), "--board", str(BOARD),
           "--out", str(out), "--workers", "2"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120

    def any_done() -> bool:
        try:
            return any(out.rglob(DONE_MARKER))
        except FileNotFoundError:  # a partial folder renamed into place while walked
            return False

    while not any_done():
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() < deadline, "no board finished within 120 s"
        time.sleep(0.02)
    kids = children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    proc.stderr.close()
    done_before = {p.parent.relative_to(out).as_posix(): p.stat().st_mtime_ns
                   for p in out.rglob(DONE_MARKER)}
    assert 1 <= len(done_before) < 4, "the kill must land mid-batch"
    assert not (out / "summary.csv").exists()
    # the pool's worker processes die with the batch (no orphan keeps writing reports)
    t = time.monotonic()
    while any(alive(k) for k in kids) and time.monotonic() - t < 10:
        time.sleep(0.05)
    assert kids and not any(alive(k) for k in kids)

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

    # a third run has nothing left to do: every board skipped, no file of it rewritten
    def board_files():
        return {p: p.stat().st_mtime_ns for name in BOARDS
                for p in (out / name).rglob("*") if p.is_file()}
    written = board_files()
    again = run_batch(stacks, BOARD, out, workers=2)
    assert all(b.skipped for b in again.boards)
    assert again.exit_code == pool_run.exit_code
    assert board_files() == written


def test_a_rig_calibration_reaches_every_board_and_its_change_redoes_them(pool_run, stacks,
                                                                          tmp_path):
    """`batch --calibration`: every board is inspected with it (a z scale of 1.03 scales
    the joints' heights), and a changed calibration file re-inspects a finished board
    instead of skipping it (its content is part of the input fingerprint)."""
    from smdinspect.calibrate import ZScaleCalibration, write_calibration

    name = "lineA/board0"
    shutil.copytree(stacks / name, tmp_path / "in" / name)

    def cal(scale):
        return write_calibration(tmp_path / "rig.cal.json", z_scale=ZScaleCalibration(
            scale=scale, known_step_mm=0.5, measured_step_mm=0.5 / scale, scale_sigma=0.001,
            step_mm=0.1, top_share=0.4, residual_rms_mm=0.002, coverage=0.9))

    out = tmp_path / "reports"
    cli_code = subprocess.run(
        [PY, "-m", "smdinspect", "-q", "batch", str(tmp_path / "in"), "--board", str(BOARD),
         "--out", str(out), "--calibration", str(cal(1.03)), "--no-spc"],
        cwd=REPO, capture_output=True, text=True, timeout=180)
    assert cli_code.returncode == pool_run.board(name).exit_code, cli_code.stderr
    ref = {j["id"]: j["measured"]["max_height_mm"]
           for j in json.loads((Path(pool_run.board(name).out_dir) / "report.json")
                               .read_text())["joints"]}
    got = {j["id"]: j["measured"]["max_height_mm"]
           for j in json.loads((out / name / "report.json").read_text())["joints"]}
    ratios = [got[k] / ref[k] for k in ref if ref[k] and got.get(k) and ref[k] > 0.1]
    assert len(ratios) >= 6 and np.median(ratios) == pytest.approx(1.03, abs=0.01)
    again = run_batch(tmp_path / "in", BOARD, out, workers=1, spc=False,
                      calibration=tmp_path / "rig.cal.json")
    assert [b.skipped for b in again.boards] == [True]
    redo = run_batch(tmp_path / "in", BOARD, out, workers=1, spc=False,
                     calibration=cal(1.0))
    assert [b.skipped for b in redo.boards] == [False]
    with pytest.raises(InputError, match="does not exist"):
        run_batch(tmp_path / "in", BOARD, out, calibration=tmp_path / "none.json")


def test_cloud_filled_reaches_every_board_and_its_change_redoes_them(pool_run, stacks,
                                                                     tmp_path):
    """`batch --cloud-filled`: each board's cloud.ply also holds the filled points
    (flagged filled = 1), the verdicts are the pool run's (joints are judged on measured
    pixels only), and turning the option off re-inspects the board instead of skipping
    it (it is part of the settings' fingerprint)."""
    import plyfile

    name = "lineA/board0"
    shutil.copytree(stacks / name, tmp_path / "in" / name)
    out = tmp_path / "reports"
    done = subprocess.run(
        [PY, "-m", "smdinspect", "-q", "batch", str(tmp_path / "in"), "--board", str(BOARD),
         "--out", str(out), "--cloud-filled", "--no-spc"],
        cwd=REPO, capture_output=True, text=True, timeout=180)
    assert done.returncode == pool_run.board(name).exit_code, done.stderr
    v = plyfile.PlyData.read(str(out / name / "cloud.ply"))["vertex"]
    assert 0 < int(v["filled"].sum()) < len(v)
    ref = json.loads((Path(pool_run.board(name).out_dir) / "report.json").read_text())
    got = json.loads((out / name / "report.json").read_text())
    assert [j["verdict"] for j in got["joints"]] == [j["verdict"] for j in ref["joints"]]
    again = run_batch(tmp_path / "in", BOARD, out, workers=1, spc=False, cloud_filled=True)
    assert [b.skipped for b in again.boards] == [True]
    plain = run_batch(tmp_path / "in", BOARD, out, workers=1, spc=False)
    assert [b.skipped for b in plain.boards] == [False]
    names = plyfile.PlyData.read(str(out / name / "cloud.ply"))["vertex"].properties
    assert "filled" not in [p.name for p in names]


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
    assert summary["executor"] == "dask-local(2 workers, tls)"
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
    with pytest.raises(InputError, match="--keep-unreliable.*not both"):
        run_batch(stacks, BOARD, tmp_path / "o", keep_unreliable=True, cloud_filled=True)
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


def test_batch_focus_options_reach_the_boards(monkeypatch, tmp_path):
    """`batch` starts from inspection's focus settings, like `inspect`, and passes the
    options given (here --prefilter and --window-px) on to every board."""
    from smdinspect import batch as batch_module
    from smdinspect import cli
    from smdinspect.pipeline import inspection_focus_config

    seen = {}

    def fake_run_batch(*args, focus_config=None, **kwargs):
        seen["focus"] = focus_config
        raise InputError("stop here")

    monkeypatch.setattr(batch_module, "run_batch", fake_run_batch)
    code = cli.main(["-q", "batch", str(tmp_path), "--board", str(BOARD), "--out",
                     str(tmp_path / "o"), "--prefilter", "auto", "--window-px", "7"])
    assert code == 2
    want = dataclasses.replace(inspection_focus_config(), prefilter_px="auto", window_px=7)
    assert seen["focus"] == want
    assert cli.main(["-q", "batch", str(tmp_path), "--board", str(BOARD), "--out",
                     str(tmp_path / "o"), "--prefilter", "wide"]) == 2
