"""`mpib dataset` under stress: shared folders, SIGTERM, bad folders and schedulers, and
the progress shown on a terminal (issue 15)."""

from __future__ import annotations

import fcntl
import json
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import time

import numpy as np
import pytest
from clirun import one_line_error, run

from mpib_validate.cards.dataset import OWNER_FILE, build_dataset, make_sample, sample_dir

SMALL = dict(family="mixed", size=(32, 24), spp=16)
CMD = [sys.executable, "-m", "mpib_validate.cli"]


def _dead_pid() -> int:
    p = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                       capture_output=True, text=True)
    return int(p.stdout)


def test_a_live_runs_temporary_folder_is_left_alone(tmp_path):
    """A second run's start-up deleted every .tmp-sample-* folder, the first run's
    in-progress sample included, and the first run then failed. Now only folders whose
    owner process is gone from this host are removed."""
    import socket

    out = tmp_path / "ds"
    out.mkdir()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        busy = out / ".tmp-sample-000007-x-0001"
        busy.mkdir()
        (busy / OWNER_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": live.pid}))
        (busy / "half-written.exr").write_bytes(b"...")
        gone = out / ".tmp-sample-000008-x-0002"
        gone.mkdir()
        (gone / OWNER_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": _dead_pid()}))
        elsewhere = out / ".tmp-sample-000009-x-0003"
        elsewhere.mkdir()
        (elsewhere / OWNER_FILE).write_text(json.dumps({"host": "another-host", "pid": 1}))
        s = build_dataset(out, 1, **SMALL)
        assert s["count"] == 1
        assert (busy / "half-written.exr").exists()  # the live run's work survives
        assert not gone.exists()
        assert elsewhere.exists()  # a Dask worker on another host may still use it
    finally:
        live.kill()
        live.wait()


def test_a_sample_finished_by_another_run_is_kept(tmp_path):
    """Two runs building the same seed: the one that finishes second keeps the first's
    sample (same seed, same files) instead of failing on the rename or deleting it."""
    from mpib_validate.cards import dataset

    out = tmp_path / "ds"
    out.mkdir()
    first = make_sample((str(out), 3, "constant", 32, 24, 16))
    final = sample_dir(out, 3)
    before = {p: p.read_bytes() for p in final.rglob("*") if p.is_file()}
    # the other run passed its "already done?" check before the first one finished
    tmp = dataset._new_tmp(out, final)
    (tmp / "done.json").write_text("{}")
    assert dataset._publish(tmp, final) is False
    assert not tmp.exists() and not first["skipped"]
    assert {p: p.read_bytes() for p in final.rglob("*") if p.is_file()} == before
    assert not (final / OWNER_FILE).exists()


def test_two_concurrent_runs_on_one_folder_both_complete(tmp_path):
    """A second run starts while the first is rendering a sample: its start-up used to
    delete that sample's folder (the first run then aborted, or published a sample
    without its scene). Both runs now complete, and every sample is whole."""
    out = tmp_path / "ds"
    first = subprocess.Popen([str(a) for a in [*CMD, "dataset", "--out", out, "--count", 2,
                                               "--size", "48x32", "--spp", 4096]],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(out.glob(".tmp-sample-*/scene/scene.json")) and time.monotonic() < deadline:
        assert first.poll() is None, first.communicate()
        time.sleep(0.02)
    second = build_dataset(out, 1, family="mixed", size=(48, 32), spp=16, start=2)
    stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert second["built"] == 1
    for name in ("sample-000000", "sample-000001", "sample-000002"):
        for f in ("done.json", "render.exr", "scene/scene.json"):
            assert (out / name / f).exists(), (name, f)
    assert not list(out.glob(".tmp-*"))


def _descendants(pid: int) -> set[int]:
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/task/{p}/children") as fh:
                kids = [int(k) for k in fh.read().split()]
        except OSError:
            kids = []
        for k in kids:
            if k not in found:
                found.add(k)
                todo.append(k)
    return found


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_sigterm_stops_the_workers_and_the_resource_tracker(tmp_path):
    """SIGTERM killed only the parent: two workers and the resource tracker lived on."""
    proc = subprocess.Popen([*CMD, "dataset", "--out", str(tmp_path / "ds"), "--count", "6",
                             "--size", "96x96", "--spp", "4096", "--workers", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    kids: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # two workers and the tracker, at work
            kids = _descendants(proc.pid)
            if len(kids) >= 3 and list((tmp_path / "ds").glob(".tmp-sample-*")):
                break
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
        assert len(kids) >= 3, kids
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
        assert proc.returncode == 143, stderr
        assert "terminated" in stderr and "Traceback" not in stderr
        deadline = time.monotonic() + 20
        while any(_alive(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [k for k in kids if _alive(k)]
    finally:
        for k in kids | {proc.pid}:
            if _alive(k):
                os.kill(k, signal.SIGKILL)


@pytest.mark.parametrize("where, message", [
    ("file", "is a file"),
    ("/sys/mpib-test-x", "/sys/mpib-test-x"),
])
def test_unusable_output_folder_is_one_line(tmp_path, where, message):
    """An existing file as --out was a FileExistsError traceback, /sys/x a PermissionError."""
    if where == "file":
        where = tmp_path / "file"
        where.write_text("x")
    line = one_line_error(*run("dataset", "--out", where, "--count", 1, "--size", "8x8",
                               "--spp", 1)[::2])
    assert message in line


def test_unreachable_scheduler_fails_fast(tmp_path):
    """An unreachable --scheduler was an OSError traceback after 30 s."""
    t0 = time.monotonic()
    line = one_line_error(*run("dataset", "--out", tmp_path / "never-made", "--count", 1,
                               "--size", "8x8", "--spp", 1, "--scheduler", "tcp://127.0.0.1:9")[::2])
    assert "--scheduler 'tcp://127.0.0.1:9'" in line and "cannot reach" in line
    assert time.monotonic() - t0 < 25  # 5 s connect timeout, plus Dask's start-up
    assert not (tmp_path / "never-made").exists()


def _on_a_terminal(args, timeout=300) -> tuple[int, str]:
    """Run the command with stdout and stderr on a pseudo-terminal; its output."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    proc = subprocess.Popen([str(a) for a in args], stdout=slave, stderr=slave, close_fds=True)
    os.close(slave)
    chunks = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.5)
        if ready:
            try:
                data = os.read(master, 65536)
            except OSError:
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    os.close(master)
    return proc.wait(timeout=30), b"".join(chunks).decode(errors="replace")


def test_progress_bars_on_a_terminal(tmp_path):
    """refocus printed nothing for minutes and dataset only its last line."""
    from mpib_validate.runtime.io.exr import channels_from_rgba, write_exr

    rgb = np.full((32, 48, 3), 0.5, np.float32)
    depth = np.full((32, 48), 4.0, np.float32)
    depth[8:20, 10:30] = 1.5
    write_exr(tmp_path / "in.exr", {**channels_from_rgba(rgb), "Depth.Z": depth})
    rc, text = _on_a_terminal([*CMD, "refocus", tmp_path / "in.exr", "-o", tmp_path / "o.exr",
                               "--blur-parameter", 20, "--focus-depth", 4])
    assert rc == 0, text
    assert "refocus:" in text and "%|" in text and "100/100" in text  # the tqdm bar
    rc, text = _on_a_terminal([*CMD, "dataset", "--out", tmp_path / "ds", "--count", 2,
                               "--size", "24x16", "--spp", 8])
    assert rc == 0, text
    assert "dataset:" in text and "sample" in text and "2/2" in text
