"""The named hard cases: each generator case, scored per method against the ray tracer.

Cases (``generate.HARD_CASES``): thin structures, hair, soft semi-transparent edges, HDR
highlights, an object near the focus plane, a near-grazing tilted plane, large blur
(radius over 10 % of the width), focus on the foreground, focus on the background.
Methods: Eq. 1 on exact layers, the MPI from colour + depth (default preset, and
without the fill), scatter, and Blender's Defocus node where bpy is installed.
"""

from __future__ import annotations

from pathlib import Path

from mpib_validate.bench.machine import finish, machine_info

METHODS = ("exact-layers (reference)", "preset-default", "mpi-no-fill", "scatter",
           "blender-defocus-node")


def _case_task(item) -> list[dict]:
    from mpib_validate.cards.generate import GeneratorSettings, generate
    from mpib_validate.bench.refocus import _scene_rows

    case, family, size, ref_spp = item
    print(f"bench hardcases: {case} ({family}, {size}x{size}) ...", flush=True)
    scene = generate(0, family, case=case, settings=GeneratorSettings(width=size, height=size))
    rows = _scene_rows(scene, case, family, ref_spp, only=METHODS)
    for r in rows:
        r["case"] = case
    return rows


def run(out: Path, quick: bool = True, executor=None) -> dict:
    from mpib_validate.executor import make_executor
    from mpib_validate.cards.generate import HARD_CASES

    out.mkdir(parents=True, exist_ok=True)
    size = 128 if quick else 384
    items = [(case, "constant" if case != "grazing" else "varying", size, 1024 if quick else 4096)
             for case in HARD_CASES]
    rows = [r for part in (executor or make_executor()).map(_case_task, items) for r in part]
    result = {"suite": "hardcases", "quick": quick, "size": size, "machine": machine_info(),
              "rows": rows}
    result["summary"] = _summarise(rows)
    return finish(out, "hardcases", result, _markdown)


def _summarise(rows):
    heads = []
    by = {(r["case"], r["method"]): r for r in rows}
    cases = sorted({r["case"] for r in rows})
    wins = [c for c in cases if ("blender-defocus-node" not in {m for (cc, m) in by if cc == c})
            or by[(c, "preset-default")]["psnr_ob"] > by[(c, "blender-defocus-node")]["psnr_ob"]]
    heads.append(f"Hard cases: the MPI from colour + depth beats Blender's Defocus node at "
                 f"occlusion boundaries in {len(wins)} of {len(cases)} cases"
                 + (f" (not: {', '.join(c for c in cases if c not in wins)})." if len(wins) < len(cases) else "."))
    return {"headlines": heads}


def _markdown(result) -> str:
    rows = result["rows"]
    cases = []
    for r in rows:
        if r["case"] not in cases:
            cases.append(r["case"])
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    lines = ["# Hard cases", "", f"{result['size']}x{result['size']}, scene seed 0 of each case; "
             "PSNR / PSNR_ob (dB) against the ray tracer, values clipped to [0, 1].", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["| case | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    by = {(r["case"], r["method"]): r for r in rows}
    for c in cases:
        cells = [f"{by[(c, m)]['psnr']:.1f} / {by[(c, m)]['psnr_ob']:.1f}" if (c, m) in by else "-"
                 for m in methods]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
