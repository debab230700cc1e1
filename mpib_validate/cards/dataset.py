"""``mpib dataset``: many generated card scenes with their ray-traced references.

Each sample is a folder ``sample-<seed>/`` holding the scene (``scene/``: JSON + EXR
textures) and its render (``render.exr``: defocused image, all-in-focus image, depth,
disparity, per-card hit layers), plus ``done.json``. A sample is built in a temporary
folder and renamed into place only when complete, so an interrupted run leaves no
half-written sample, and a rerun skips every sample that has its ``done.json``.

Runs may share a folder: each temporary folder records its owner (host and process),
and a run removes only those whose owner process is gone from this host (left by an
interrupted run), never another live run's. Two runs that build the same seed keep the
first complete sample (the same seed gives the same files).
Samples are independent, so any executor (:mod:`mpib_validate.executor`) can build them;
the same seed gives the same scene and the same pixels whichever runs it.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import socket
import time
from pathlib import Path

from mpib_validate.runtime.io.atomic import OutputError

FAMILIES = ("constant", "varying", "mixed")


def sample_dir(out, seed: int) -> Path:
    return Path(out) / f"sample-{seed:06d}"


def family_of(family: str, seed: int) -> str:
    return ("constant", "varying")[seed % 2] if family == "mixed" else family


OWNER_FILE = ".owner"
TMP_PREFIX = ".tmp-sample-"


def _new_tmp(out: Path, final: Path) -> Path:
    """A temporary folder for ``final``, owned by this process (see :func:`_owner_gone`)."""
    tmp = Path(out) / f".tmp-{final.name}-{os.getpid()}-{secrets.token_hex(4)}"
    tmp.mkdir(parents=True)
    (tmp / OWNER_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid()}))
    return tmp


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    try:  # a zombie is gone too
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def _owner_gone(tmp: Path) -> bool:
    """Whether the run that made ``tmp`` has ended on this host (so the folder is a
    leftover): its owner file names another host (unknown: keep), or a process that is
    no longer alive. Folders without an owner file (older versions) name their pid."""
    try:
        owner = json.loads((tmp / OWNER_FILE).read_text())
        host, pid = owner["host"], int(owner["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        m = re.search(r"-(\d+)-[0-9a-f]+$", tmp.name)
        if m is None:
            return False
        host, pid = socket.gethostname(), int(m.group(1))
    return host == socket.gethostname() and pid != os.getpid() and not _pid_alive(pid)


def _discard(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def _publish(tmp: Path, final: Path) -> bool:
    """Rename the complete ``tmp`` onto ``final``; False if another run finished the
    same sample first (``tmp`` is then discarded: the files would be the same)."""
    for _ in range(3):
        try:
            os.rename(tmp, final)  # atomic; refused when final is a non-empty folder
            return True
        except OSError:
            if (final / "done.json").exists():
                _discard(tmp)
                return False
            # an incomplete folder in the way (not made by this version): move it aside
            aside = final.parent / f".tmp-{final.name}-stale-{secrets.token_hex(4)}"
            try:
                os.rename(final, aside)
            except OSError:
                continue
            _discard(aside)
    raise OSError(f"cannot move the finished sample into '{final}'")


def make_sample(item: tuple) -> dict:
    """Build one sample: ``item = (out, seed, family, width, height, spp)``."""
    from mpib_validate.runtime import samples
    from mpib_validate.cards import trace
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.cards.generate import GeneratorSettings, generate
    from mpib_validate.cards.render_io import write_render
    from mpib_validate.cards.scene import save_scene

    out, seed, family, width, height, spp = item
    final = sample_dir(out, seed)
    if (final / "done.json").exists():
        return {"seed": seed, "skipped": True}
    t0 = time.perf_counter()
    tmp = _new_tmp(Path(out), final)
    try:
        scene = generate(seed, family_of(family, seed),
                         settings=GeneratorSettings(width=width, height=height))
        save_scene(scene, tmp / "scene")
        result = trace.render(scene, samples.stratified(spp, seed=seed), notices=False)
        write_render(tmp / "render.exr", result, scene, preview=False)
        info = {"seed": seed, "family": family_of(family, seed), "size": [width, height],
                "spp": spp, "cards": len(scene.cards), "backend": result.meta["backend"],
                "max_blur_radius_px": scene.max_blur_radius()}
        write_text(tmp / "done.json", json.dumps(info, indent=2) + "\n")
        (tmp / OWNER_FILE).unlink()
        built = _publish(tmp, final)
    finally:
        if tmp.exists():
            _discard(tmp)
    return {**info, "skipped": not built, "seconds": time.perf_counter() - t0}


def build_dataset(out, count: int, family: str = "mixed", size=(256, 256), spp: int = 1024,
                  start: int = 0, executor=None, progress=None) -> dict:
    """Build (or complete) a dataset of ``count`` samples from seed ``start`` on.

    ``progress(result)``, if given, is called as each sample is done (built or skipped).
    """
    from mpib_validate.runtime.io.atomic import write_text
    from mpib_validate.executor import make_executor

    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if count < 1 or start < 0:
        raise ValueError("count must be >= 1 and start >= 0")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"dataset folder '{out}' is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot make the dataset folder '{out}': {exc.strerror}") from None
    for stale in out.glob(TMP_PREFIX + "*"):  # left by an interrupted run, not a live one
        if stale.is_dir() and _owner_gone(stale):
            _discard(stale)
    items = [(str(out), seed, family, int(size[0]), int(size[1]), int(spp))
             for seed in range(start, start + count)]
    executor = executor or make_executor()
    results = executor.map(make_sample, items, progress)
    done = sorted(p.name for p in out.glob("sample-*") if (p / "done.json").exists())
    summary = {"count": len(done), "built": sum(not r["skipped"] for r in results),
               "skipped": sum(r["skipped"] for r in results), "executor": executor.kind,
               "samples": done}
    write_text(out / "index.json", json.dumps(summary, indent=2) + "\n")
    return summary
