"""Benchmark of the physically based references: time and noise against sample count.

Mitsuba 3 (each variant that runs here) and Cycles (CPU) render the generated scene of
each family; the noise of one render is estimated from two seeds,
``sqrt(mean((I_1 - I_2)^2) / 2)`` in linear radiance. The "constant" scenes are LDR,
the "varying" ones carry HDR highlights (peak ~170), hence their far larger RMSE.
"""

from __future__ import annotations

from pathlib import Path

from mpib_validate.bench.machine import finish, machine_info


def _mitsuba_rows(scene, spps, variant):
    import mitsuba_scenes

    return [{"engine": "mitsuba", "variant": r["variant"], "spp": r["spp"], "seconds": r["seconds"],
             "rmse": r["rmse"]} for r in mitsuba_scenes.noise_vs_spp(scene, spps, variant)]


def _cycles_rows(scene, spps):
    from mpib_validate.blender import cycles

    return [{"engine": "cycles", "variant": "cpu", "spp": r["spp"], "seconds": r["seconds"],
             "rmse": r["noise_rmse"]} for r in cycles.noise_vs_spp(scene, spps)]


def run(out: Path, quick: bool = True) -> dict:
    import importlib.util

    from mpib_validate.cards.generate import FAMILIES, GeneratorSettings, generate

    out.mkdir(parents=True, exist_ok=True)
    sizes = (256,) if quick else (256, 512)
    spps = (16, 64, 256, 1024) if quick else (16, 64, 256, 1024, 4096)
    rows = []
    have_mi = importlib.util.find_spec("mitsuba") is not None
    have_bpy = importlib.util.find_spec("bpy") is not None
    if have_mi:
        import mitsuba_scenes

        variants = [mitsuba_scenes.choose_variant().name]
        if "scalar_rgb" not in variants:
            variants.append("scalar_rgb")
    for size in sizes:
        for family in FAMILIES:
            scene = generate(0, family, settings=GeneratorSettings(width=size, height=size))
            label = f"{family} {size}x{size}"
            print(f"bench references: {label} ...", flush=True)
            if have_mi:
                for v in variants:
                    few = spps[:1] if v == "scalar_rgb" else spps  # scalar: ~10 s per 256^2 x 16 spp
                    for r in _mitsuba_rows(scene, few, v):
                        rows.append({"scene": label, "family": family, "size": size, **r})
            if have_bpy:
                for r in _cycles_rows(scene, spps[:-1] if quick else spps):
                    rows.append({"scene": label, "family": family, "size": size, **r})
    result = {"suite": "references", "quick": quick, "machine": machine_info(), "rows": rows,
              "missing": [n for n, ok in (("mitsuba", have_mi), ("bpy", have_bpy)) if not ok]}
    result["summary"] = _summarise(rows)
    return finish(out, "references", result, _markdown)


def _summarise(rows):
    heads = []
    for engine, variant in sorted({(r["engine"], r["variant"]) for r in rows}):
        rs = [r for r in rows if r["engine"] == engine and r["variant"] == variant
              and r["family"] == "constant" and r["size"] == 256]
        if len(rs) >= 2:
            # noise ~ 1/sqrt(spp): samples needed for RMSE 1e-3, and the time that takes
            last = max(rs, key=lambda r: r["spp"])
            need = last["spp"] * (last["rmse"] / 1e-3) ** 2
            t = last["seconds"] * need / last["spp"]
            heads.append(f"{engine} {variant}, constant 256x256: RMSE {last['rmse']:.2g} at "
                         f"{last['spp']} spp in {last['seconds']:.2f} s; RMSE 1e-3 needs ~{need:.0f} "
                         f"spp, ~{t:.1f} s (1/sqrt(spp) extrapolation).")
    return {"headlines": heads}


def _markdown(result) -> str:
    m = result["machine"]
    lines = ["# References: time and noise against samples per pixel", "",
             f"Machine: {m.get('processor')}, {m.get('affinity_cores', m.get('cpu_count'))} cores; "
             f"mitsuba {m.get('mitsuba', '-')}, bpy {m.get('bpy', '-')}.", ""]
    if result["missing"]:
        lines += [f"Not measured here (not installed): {', '.join(result['missing'])}.", ""]
    lines += [f"- {h}" for h in result["summary"]["headlines"]] + [""]
    lines += ["| scene | engine | variant | spp | time (s) | noise RMSE |", "|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['engine']} | {r['variant']} | {r['spp']} | "
                     f"{r['seconds']:.3f} | {r['rmse']:.3g} |")
    return "\n".join(lines) + "\n"
