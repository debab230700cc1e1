"""`mpib dataset`: atomic samples, resume, and the same results on every executor."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from mpib_validate.cards.dataset import build_dataset, sample_dir
from mpib_validate.executor import make_executor
from mpib_validate.runtime.io.exr import read_exr

SMALL = dict(family="mixed", size=(32, 24), spp=16)


def _pixels(folder):
    img = read_exr(folder / "render.exr")
    return {k: v for k, v in img.channels.items()}


def test_resume_skips_finished_samples_and_cleans_interruptions(tmp_path):
    out = tmp_path / "ds"
    s = build_dataset(out, 3, **SMALL)
    assert s["count"] == 3 and s["built"] == 3
    stamp = {p: p.stat().st_mtime_ns for p in out.glob("sample-*/render.exr")}
    # an interrupted run: a half-built temporary folder whose process is gone, and one
    # sample lost
    import shutil
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    (out / f".tmp-sample-000009-{dead}-abcd").mkdir()

    shutil.rmtree(sample_dir(out, 1))
    s = build_dataset(out, 3, **SMALL)
    assert s == {**s, "count": 3, "built": 1, "skipped": 2}
    assert not list(out.glob(".tmp-*"))
    for p, t in stamp.items():
        if "000001" not in str(p):
            assert p.stat().st_mtime_ns == t  # finished samples were not redone
    assert json.loads((sample_dir(out, 1) / "done.json").read_text())["family"] == "varying"


@pytest.mark.parametrize("executor", ["processes", "dask-local"])
def test_every_executor_gives_the_same_samples(tmp_path, executor):
    """Same seeds, same scenes and the same pixels whether built in this process, in
    local processes or on a Dask LocalCluster."""
    if executor == "dask-local":
        pytest.importorskip("distributed")
        ex = make_executor(workers=2, scheduler="local")
    else:
        ex = make_executor(workers=2)
    a = build_dataset(tmp_path / "a", 2, **SMALL)
    b = build_dataset(tmp_path / "b", 2, executor=ex, **SMALL)
    assert a["samples"] == b["samples"] and b["executor"] in ("processes", "dask")
    for name in a["samples"]:
        pa, pb = _pixels(tmp_path / "a" / name), _pixels(tmp_path / "b" / name)
        assert pa.keys() == pb.keys()
        for k in pa:
            np.testing.assert_array_equal(pa[k], pb[k])
        sa = (tmp_path / "a" / name / "scene" / "scene.json").read_bytes()
        assert sa == (tmp_path / "b" / name / "scene" / "scene.json").read_bytes()


def test_bad_arguments():
    with pytest.raises(ValueError, match="family"):
        build_dataset(os.devnull, 1, family="tilted")
