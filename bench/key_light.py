"""The key light on captures lit from several directions (issue 51): found vs true direction, held-out quality.

    python bench/key_light.py                        # 7 captures x (before, after) x seeds 0 1, ~25 min on 2 cores
    python bench/key_light.py --seeds 0 --captures pbr-side lambert-side
    python bench/key_light.py --tiny                 # seconds, to check the script
    python bench/key_light.py --report --variants quality check   # the tables (and --pictures) of saved runs
    python bench/key_light.py --asset ASSETS/Fox.glb --captures pbr-front pbr-side pbr-backtop pbr-env \
        lambert-front --variants control quality check check-noprior after --pictures pbr-side pbr-env
                                                     # an asset the recipe was not tuned on, with the control
    python bench/key_light.py --asset ASSETS/Fox.glb --iters 1500 --seeds 0 --name key_light_Fox_1500 \
        --work runs/bench-key_light-Fox-1500 --captures ... --variants control quality check after

Captures: CesiumMan (monocular turn, driving mesh Taubin-smoothed 5 iterations as the demo's), rendered by the
path tracer (``meshsplat synth --renderer pbr``: sky + a soft key light) with the key light from the front (the
project's default direction), the side, behind and above, and no key at all (the sky alone, ``--key 0``), and by
the Lambert rasterizer (one directional light + ambient, no shadows) from the first three. Each capture's
``light_dir`` is in its meta (``manifest.json``) and in the table. Path-traced held-out frames are scored against
the same frames rendered again with ``--ref-spp`` samples per pixel.

Variants, the same code: ``before`` is the quality recipe with the key light's search as it was (``shading.key_seed
=false shading.key_check_frames=0``); ``after`` seeds the search from the learned irradiance and checks the key
(``shading.key_seed=true shading.key_check_frames=4``); ``check`` the search as it was, then the check (the quality
recipe since issue 51's unseen-asset bench). ``control`` is the ``paper`` recipe (the previous default) with the
same schedule; ``quality`` the quality recipe as it was measured there (no check: the same runs as ``before``);
``check-noprior`` the check with the albedo prior off; ``agree45`` the 45-degree test (the recipe before
``shading.key_snap_deg``), ``snap15`` the recipe since (a key 15-45 degrees from the irradiance moves to it). All
at ``--iters`` iterations with ``shading.key_iter`` a fifth of them (the key aligned at 60%). Per run: the key's
final direction (kept, or dropped: folded into the SH2 irradiance), its angle to the true light, the learned
irradiance's own direction (``Shading.key_seed`` of the final lighting) and its angle, the check's gain, and per
held-out split subject PSNR (white), full-image PSNR (white), LPIPS in the mask, and the silhouette band on black:
its share of the squared error, the part of it that is the edge's coverage (the band's error with the avatar's
colour but the true mask, subtracted), the mean |alpha - mask| in it with its sign, and the driving mesh's own
|coverage - mask|. Saves bench/results/key_light-<host>.json (``key_light_<asset>`` for another ``--asset``) after
every run; a rerun reuses the captures and finished runs. ``--asset``: a bundled asset's name or a .glb path (any
animated glTF ``meshsplat synth`` reads; its held-out novel-clip split is scored too). ``--pictures CAP ...``:
bench/reports/images/<name>_<CAP>.png, a held-out view of seed 0 (``--picture-seed S``: of seed S,
<name>_<CAP>_sS.png): the reference, then each variant named.
Reports: bench/reports/key_light.md (CesiumMan), key_light_unseen.md (Fox, with the control).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path

from _machine import machine_info, results_path
from quality_pbr import _mesh_coverage
from quality_pbr import _schedule as _demo_schedule

FRONT = (0.35, 0.75, 0.55)  # meshsplat.synth's default light
CAPTURES: dict[str, dict] = {
    "pbr-front": {"renderer": "pbr", "light": FRONT},
    "pbr-side": {"renderer": "pbr", "light": (1.0, 0.25, 0.0)},
    "pbr-backtop": {"renderer": "pbr", "light": (-0.25, 0.8, -0.55)},
    "pbr-env": {"renderer": "pbr", "light": FRONT, "key": 0.0},  # the sky alone: no directional light
    "lambert-front": {"renderer": "lambert", "light": FRONT},
    "lambert-side": {"renderer": "lambert", "light": (1.0, 0.25, 0.0)},
    "lambert-backtop": {"renderer": "lambert", "light": (-0.25, 0.8, -0.55)},
}
_NO_SNAP = "shading.key_snap_deg=0"
_AGREE45 = ["shading.key_check_frames=0", "shading.key_agree_deg=45", _NO_SNAP]  # the quality recipe before snap
_SNAP15 = ["shading.key_check_frames=0", "shading.key_agree_deg=45", "shading.key_snap_deg=15"]  # the recipe since
VARIANTS = {  # each pins the key's tests as it was measured (shading.key_agree_deg, key_snap_deg); control: paper
    "before": ["shading.key_seed=false", "shading.key_check_frames=0", "shading.key_agree_deg=0", _NO_SNAP],
    "after": ["shading.key_seed=true", "shading.key_check_frames=4", "shading.key_agree_deg=0", _NO_SNAP],
    # the old search, then the check
    "check": ["shading.key_seed=false", "shading.key_check_frames=4", "shading.key_agree_deg=0", _NO_SNAP],
    "nokey": ["shading.occlusion=none"],  # no key light at all (a reference; only when named)
    "control": [],  # the paper recipe (the previous default), same code and schedule
    # the quality recipe before shading.key_agree_deg (= before), as measured against the control
    "quality": ["shading.key_check_frames=0", "shading.key_agree_deg=0", _NO_SNAP],
    "check-noprior": ["shading.key_check_frames=4", "albedo_prior.enabled=false", "shading.key_agree_deg=0", _NO_SNAP],
    # the key kept only within 20 / 45 degrees of the learned irradiance's direction (shading.key_agree_deg)
    "agree": ["shading.key_check_frames=0", "shading.key_agree_deg=20", "shading.key_snap_deg=0"],
    "agree45": _AGREE45,
    "after-agree": ["shading.key_seed=true", "shading.key_check_frames=4", "shading.key_agree_deg=20", _NO_SNAP],
    # the seeded search (from the learned irradiance's direction), then the 45-degree test, no check
    "seeded": ["shading.key_seed=true", *_AGREE45],
    # the key moved to the learned irradiance's direction where they disagree by more than 15 degrees (the recipe since)
    "snap15": _SNAP15,
    # every key farther than 15 degrees from the learned irradiance moves there: none dropped
    "snapall": ["shading.key_check_frames=0", "shading.key_agree_deg=180", "shading.key_snap_deg=15"],
    # the silhouette band: antialiased opacity (the 0.3 px^2 screen-space blur compensated), a heavier mask loss
    "aa": [*_AGREE45, "model.antialiased=true"],
    "snap15aa": [*_SNAP15, "model.antialiased=true"],
    "mask03": [*_AGREE45, "mask_loss.weight=0.3"],
    # LPIPS's backbone in float32 / bfloat16 (issue 47: ~2x cheaper LPIPS on CPUs with native bf16)
    "lpips_fp32": ["loss.lpips_precision=float32", "shading.key_agree_deg=0", _NO_SNAP],
    "lpips_bf16": ["loss.lpips_precision=bfloat16", "shading.key_agree_deg=0", _NO_SNAP],
}
RECIPE = {"control": "paper"}  # the recipe of each variant; quality otherwise


def _schedule(iterations: int) -> tuple[str, ...]:
    """quality_pbr's short schedule (the demo's, scaled to ``iterations``), the key's stages a fifth of it."""
    return (*_demo_schedule(iterations), f"shading.key_iter={max(1, iterations // 5)}", "device=cpu")


def _capture(name: str, args, work: Path, spp: int | None = None) -> Path:
    """Capture ``name``; with ``spp`` other than ``args.spp`` its held-out frames only (the references)."""
    from meshsplat.synth import synthesize
    from meshsplat.synth.pbr import PbrSettings

    c = CAPTURES[name]
    spp = args.spp if spp is None else spp
    data = work / (f"data-{name}" + (f"-spp{spp}" if spp != args.spp else ""))
    if (data / "manifest.json").exists():
        return data
    held_out = None
    if spp != args.spp:  # the references: every held-out split of the training capture
        main = json.loads((work / f"data-{name}" / "manifest.json").read_text())
        held_out = [s for s in main["splits"] if s != "train"]
    synthesize(
        args.asset,
        data,
        rig="monocular-turn",
        frames=args.frames,
        resolution=args.resolution,
        test_frames=args.test_frames,
        test_views=2,
        test_view_frames=max(2, args.test_frames // 2),
        driver_smooth=5,
        renderer=c["renderer"],
        pbr=PbrSettings(spp=spp, key=c.get("key", PbrSettings.key)),
        light_dir=c["light"],
        overwrite=True,
        splits=held_out,
        threads=1,
    )
    return data


def _angle(a, b) -> float | None:
    if a is None or b is None:
        return None
    dot = sum(x * y for x, y in zip(a, b, strict=True))
    na, nb = math.sqrt(sum(x * x for x in a)), math.sqrt(sum(x * x for x in b))
    return math.degrees(math.acos(max(-1.0, min(1.0, dot / (na * nb)))))


def _key(run: Path, light: list[float] | None) -> dict:
    """The run's key light: where it ended (kept or dropped), the irradiance's own direction, angles to ``light``."""
    import torch

    from meshsplat.gaussians.shading import irradiance_direction
    from meshsplat.run_folder import load_run

    loaded = load_run(run)
    sh = loaded.avatar.shading
    if sh is None:  # no shading component (the paper recipe)
        return {"kept": None, "found": None, "irradiance": None, "log": {}, "found_deg": None, "irradiance_deg": None}
    kept = sh.occlusion == "key" and sh.directions is not None
    found = sh.directions[0] if kept else sh.dropped_key  # type: ignore[index]
    ckpt = torch.load(sorted((run / "checkpoints").glob("ckpt_*.pt"))[-1], map_location="cpu", weights_only=False)
    state = ckpt.get("state", ckpt)
    log = ((state.get("components") or {}).get("shading") or {}).get("key_log", {})
    irr = irradiance_direction(sh.unshadowed_coeffs() if kept else sh.coeffs.detach())
    out = {
        "kept": bool(kept),
        "found": None if found is None else [round(float(x), 4) for x in found],
        "irradiance": [round(float(x), 4) for x in irr],
        "log": log,
    }
    out["found_deg"] = _angle(out["found"], light)
    out["irradiance_deg"] = _angle(out["irradiance"], light)
    for k in ("seed", "strongest"):
        if k in log:
            out[f"{k}_deg"] = _angle(log[k], light)
    return out


def _score(run: Path, data: Path, ref: Path) -> dict:
    """Per held-out split: mean subject PSNR (white) and LPIPS in the mask against ``ref``'s images, and where
    the error on black is: the silhouette band's share of it (``meshsplat.metrics.budget``), in the band the
    mean |alpha - mask| and its sign (> 0: the avatar spills over the edge) and the driving mesh's own
    |coverage - mask|."""
    import torch

    from meshsplat.data import open_dataset
    from meshsplat.metrics import lpips, lpips_available, psnr
    from meshsplat.metrics.budget import BUDGET_REGIONS, error_budget, silhouette_regions
    from meshsplat.metrics.subject import subject_metrics
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    loaded = load_run(run)
    ds, refs = loaded.open_dataset(data), open_dataset(ref)
    by_name = {refs.frame_info(j)["name"]: j for j in range(len(refs))}
    lp = (lambda a, b: lpips(a, b)) if lpips_available("alex") else None
    white, black = torch.ones(3), torch.zeros(3)
    out = {}
    for split in [s for s in ds.split_names if s != "train"]:
        rows, sse = [], dict.fromkeys((*BUDGET_REGIONS, "band_colour"), 0.0)
        for i in ds.split(split):
            fr = ds[i]
            target = refs[by_name[ds.frame_info(i)["name"]]]
            with torch.no_grad():
                img = loaded.avatar.render(fr.vertices, fr.camera, white).image.float().clamp(0, 1)
                on_black = loaded.avatar.render(fr.vertices, fr.camera, black)
            gt = composite(target.image, target.mask, white)
            row = {**subject_metrics(img, gt, target.mask, lp), "psnr_full": float(psnr(img, gt))}
            budget = error_budget(
                on_black.image.float().clamp(0, 1), composite(target.image, target.mask, black), target.mask
            )
            for r in BUDGET_REGIONS:
                sse[r] += budget[f"sse_{r}"]
            band = silhouette_regions(target.mask)["band"]
            # the band's error with the avatar's own colour but the true coverage (where it covers anything):
            # what is left is colour; the rest of the band's error is the coverage (edge alpha)
            a = on_black.alpha.float()
            recovered = torch.where(a > 0.05, on_black.image.float() / a.clamp_min(0.05) * target.mask, on_black.image)
            gt_black = composite(target.image, target.mask, black)
            sse["band_colour"] += float((recovered.clamp(0, 1) - gt_black).pow(2).sum(-1)[band].sum())
            d = (on_black.alpha.float() - target.mask)[band]
            mesh = _mesh_coverage(fr.vertices, ds.faces, fr.camera)
            row.update(
                alpha_band_abs=float(d.abs().mean()),
                alpha_band_bias=float(d.mean()),
                mesh_band_abs=float((mesh - target.mask)[band].abs().mean()),
            )
            rows.append(row)
        lps = [r["lpips_mask"] for r in rows if r["lpips_mask"] is not None]  # None: a crop too small
        total = sum(sse[r] for r in BUDGET_REGIONS) or 1.0
        out[split] = {
            # the band's share of the error that is the edge's coverage, not its colour
            "band_coverage_share": 1.0 - sse["band_colour"] / sse["band"] if sse["band"] > 0 else 0.0,
            **{
                k: sum(r[k] for r in rows) / len(rows)
                for k in ("psnr_mask", "psnr_full", "alpha_band_abs", "alpha_band_bias", "mesh_band_abs")
            },
            "lpips_mask": sum(lps) / len(lps) if lps else None,
            **{f"share_{r}": sse[r] / total for r in BUDGET_REGIONS},
            "frames": len(rows),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", nargs="*", default=list(CAPTURES), choices=list(CAPTURES))
    ap.add_argument("--variants", nargs="*", default=["before", "after"], choices=list(VARIANTS))
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--test-frames", type=int, default=4)
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--n-init", type=int, default=2000)
    ap.add_argument("--spp", type=int, default=16, help="pbr: samples per pixel of the training capture")
    ap.add_argument("--ref-spp", type=int, default=64, help="pbr: samples per pixel of the held-out references")
    ap.add_argument("--tiny", action="store_true", help="seconds: 32 px, 6 frames, 40 iterations, 4 spp")
    ap.add_argument("--work", help="default runs/bench-key_light[-<asset>][-tiny]")
    ap.add_argument("--name", help="results name, default key_light[_<asset>][_tiny]")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--asset", default="CesiumMan", help="bundled asset name or .glb path (default CesiumMan)")
    ap.add_argument("--pictures", nargs="*", default=[], help="captures to picture (a held-out view)")
    ap.add_argument("--picture-seed", type=int, default=0, help="the seed of the runs pictured (default 0)")
    ap.add_argument("--report", action="store_true", help="train nothing: the tables and pictures of saved runs")
    args = ap.parse_args()
    stem = Path(args.asset).stem
    name, work = (
        ("key_light", "runs/bench-key_light")
        if stem == "CesiumMan"
        else (f"key_light_{stem}", f"runs/bench-key_light-{stem}")
    )
    if args.tiny:
        args.resolution, args.frames, args.test_frames, args.iters, args.spp, args.ref_spp = 32, 6, 2, 40, 4, 8
        args.n_init, name, work = 500, name + "_tiny", work + "-tiny"
    args.name, args.work = args.name or name, args.work or work

    import torch

    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer

    torch.set_num_threads(args.threads)
    sizes = replace(
        PRESETS["default"],
        frames=args.frames,
        resolution=args.resolution,
        iterations=args.iters,
        n_init=args.n_init,
        overrides=_schedule(args.iters),
    )
    work = Path(args.work)
    out = results_path(args.name)
    previous = json.loads(out.read_text()) if out.exists() else {}
    rows: dict = previous.get("captures", {}) if previous.get("args", {}).get("iters") == args.iters else {}
    t_all = time.perf_counter()
    for seed in [] if args.report else args.seeds:
        for cap in args.captures:
            t0 = time.perf_counter()
            data = _capture(cap, args, work)
            meta = json.loads((data / "manifest.json").read_text()).get("meta", {})
            renderer = meta.get("renderer", {})
            directional = CAPTURES[cap].get("key", 1.0) > 0
            light = meta.get("light_dir") if directional else None
            ref = data
            if CAPTURES[cap]["renderer"] == "pbr" and args.ref_spp != args.spp:
                ref = _capture(cap, args, work, spp=args.ref_spp)
            row = rows.setdefault(cap, {"runs": {}})
            row.update({"light_dir": meta.get("light_dir"), "directional": directional, "renderer": renderer})
            print(f"[{cap}] capture ready ({time.perf_counter() - t0:.0f} s)", flush=True)
            for variant in args.variants:
                name = f"{variant}_s{seed}"
                run = work / f"{cap}-{name}"
                recipe = RECIPE.get(variant, "quality")
                cfg = demo_train_config(
                    data, run, sizes, [*VARIANTS[variant], f"seed={seed}"], progress=False, recipe=recipe
                )
                t0 = time.perf_counter()
                trainer = Trainer(cfg, resume=True)
                finished = trainer.iteration >= cfg.iterations
                trainer.train()
                train_s = time.perf_counter() - t0
                if finished:
                    train_s = row["runs"].get(name, {}).get("train_s", train_s)
                row["runs"][name] = {
                    "variant": variant,
                    "recipe": recipe,
                    "seed": seed,
                    "overrides": VARIANTS[variant],
                    "train_s": train_s,
                    "key": _key(run, light),
                    "splits": _score(run, data, ref),
                }
                k = row["runs"][name]["key"]
                print(
                    f"[{cap}/{name}] {train_s:.0f} s; key {_kept(k)}, "
                    f"found {k['found_deg']}, irradiance {k['irradiance_deg']}; "
                    + ", ".join(f"{s} {m['psnr_mask']:.2f}" for s, m in row["runs"][name]["splits"].items()),
                    flush=True,
                )
                shown = {**vars(args), "asset": _shown(args.asset)}  # no machine path in the results
                out.write_text(
                    json.dumps({"machine": machine_info(), "args": shown, "captures": rows}, indent=2) + "\n"
                )
    print(f"\n{args.iters} iterations, {args.resolution} px, {time.perf_counter() - t_all:.0f} s")
    rows = {c: r for c, r in rows.items() if c in args.captures}
    _table(rows)
    _summary(rows, args.variants)
    for cap in args.pictures:
        _picture(cap, args, work, args.variants, args.picture_seed)
    print(f"saved {out}")


def _shown(asset: str) -> str:
    """A bundled asset's name, or ``ASSETS/<file>`` for a path (results and reports name no machine path)."""
    return asset if "/" not in asset and "." not in asset else f"ASSETS/{Path(asset).name}"


def _gain(k: dict) -> float | None:
    """How much of the check frames' L1 error the key's shadow takes away, % (None: no check ran)."""
    e = (k.get("log") or {}).get("check_errors")
    return None if not e else 100 * (e["off"] - e["key"]) / e["off"]


def _kept(k: dict) -> str:
    return "none" if k["kept"] is None else "kept" if k["kept"] else "dropped"


def _picture(cap: str, args, work: Path, variants: list[str], seed: int = 0) -> None:
    """bench/reports/images/<name>_<cap>[_s<seed>].png: the first held-out view frame of the runs of ``seed``, on
    white, cropped to the subject and enlarged (nearest): the reference, then each of ``variants``; a label strip
    above each."""
    import torch

    from _sheets import label_sheet
    from meshsplat.data import open_dataset
    from meshsplat.render.background import composite
    from meshsplat.run_folder import load_run

    data = work / f"data-{cap}"
    ref = work / f"data-{cap}-spp{args.ref_spp}"
    ref = ref if ref.exists() else data
    refs = open_dataset(ref)
    split = "test_views" if "test_views" in refs.split_names else "test_frames"
    j = refs.split(split)[0]
    name = refs.frame_info(j)["name"]
    white = torch.ones(3)
    t = refs[j]
    panels, labels = [composite(t.image, t.mask, white)], ["ground truth"]
    for v in variants:
        run = work / f"{cap}-{v}_s{seed}"
        if not (run / "checkpoints").exists():
            continue
        loaded = load_run(run)
        ds = loaded.open_dataset(data)
        i = next(k for k in ds.split(split) if ds.frame_info(k)["name"] == name)
        fr = ds[i]
        with torch.no_grad():
            panels.append(loaded.avatar.render(fr.vertices, fr.camera, white).image.float().clamp(0, 1))
        labels.append(v)
    ys, xs = torch.nonzero(t.mask[..., 0] > 0.5, as_tuple=True)  # the subject's box, 3 px around it
    y0, y1 = max(0, int(ys.min()) - 3), min(t.mask.shape[0], int(ys.max()) + 4)
    x0, x1 = max(0, int(xs.min()) - 3), min(t.mask.shape[1], int(xs.max()) + 4)
    scale = max(2, 200 // max(y1 - y0, x1 - x0))
    sheet = label_sheet([[(label, img[y0:y1, x0:x1]) for img, label in zip(panels, labels, strict=True)]], scale, 90)
    stem = f"{args.name}_{cap}" + (f"_s{seed}" if seed else "")
    path = Path(__file__).resolve().parent / "reports" / "images" / f"{stem}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path, optimize=True)
    print(f"picture {path.name} ({split} {name}): {', '.join(labels)}")


SPLITS = ("test_frames", "test_views", "test_clip")


def _summary(rows: dict, variants: list[str]) -> None:
    """Markdown: per capture and variant, seed means of subject PSNR, full PSNR and LPIPS per split, Δ subject
    PSNR against ``quality`` (or the first variant) with the noise (half the larger seed-to-seed spread), and
    which variants win or tie on every capture-split against ``quality``."""
    base = "quality" if "quality" in variants else variants[0]

    def cell(cap: str, v: str, sp: str, key: str) -> list[float] | None:
        vals = [r["splits"][sp][key] for r in rows[cap]["runs"].values() if r["variant"] == v and sp in r["splits"]]
        vals = [x for x in vals if x is not None]
        return vals or None

    def mean(x):
        return None if not x else sum(x) / len(x)

    def half(x):
        return 0.0 if not x or len(x) < 2 else (max(x) - min(x)) / 2

    print(
        "\n| capture | light_dir | variant | key kept | found° | check gain % | "
        + " | ".join(f"{sp} subject PSNR (Δ vs {base}) / full PSNR / LPIPS" for sp in SPLITS)
        + " |"
    )
    print("|---|---|---|---|---|---|" + "---|" * len(SPLITS))
    verdict: dict[str, list] = {v: [] for v in variants if v != base}
    for cap, r in rows.items():
        ld = "sky only" if not r.get("directional") else ",".join(f"{x:.2f}" for x in r["light_dir"])
        for v in variants:
            runs = [x for x in r["runs"].values() if x["variant"] == v]
            if not runs:
                continue
            runs.sort(key=lambda x: x["seed"])
            kept = ", ".join(_kept(x["key"]) for x in runs)
            found = ", ".join(_fmt(x["key"]["found_deg"]) for x in runs)
            gain = ", ".join(_fmt(_gain(x["key"]), ".2f") for x in runs)
            cells = []
            for sp in SPLITS:
                p = cell(cap, v, sp, "psnr_mask")
                if p is None:
                    cells.append("-")
                    continue
                b = cell(cap, base, sp, "psnr_mask")
                noise = max(half(p), half(b))
                d = "" if b is None else (f" (±{noise:.2f})" if v == base else f" ({mean(p) - mean(b):+.2f})")
                if v != base and b is not None:
                    verdict[v].append((cap, sp, mean(p) - mean(b), noise))
                cells.append(
                    f"{mean(p):.2f}{d} / {_fmt(mean(cell(cap, v, sp, 'psnr_full')), '.2f')} / "
                    f"{_fmt(mean(cell(cap, v, sp, 'lpips_mask')), '.4f')}"
                )
            print(f"| {cap} | {ld} | {v} | {kept} | {found} | {gain} | " + " | ".join(cells) + " |")
    print(f"\nagainst {base} (subject PSNR; a loss is a Δ below minus the noise):")
    for v, ds in verdict.items():
        if not ds:
            continue
        losses = [f"{c}/{sp} {d:+.2f} (±{n:.2f})" for c, sp, d, n in ds if d < -n]
        avg = sum(d for _, _, d, _ in ds) / len(ds)
        print(f"- {v}: mean Δ {avg:+.3f} dB over {len(ds)} capture-splits; losses beyond noise: {losses or 'none'}")


def _fmt(x, f=".1f") -> str:
    return "-" if x is None else format(x, f)


def _table(rows: dict) -> None:
    """Markdown: per capture and variant (seeds side by side), key kept, angles, PSNR/LPIPS per split."""
    print(
        "| capture | light_dir | run | key | found° | irradiance° | test_frames PSNR / LPIPS | test_views PSNR / LPIPS |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for cap, r in rows.items():
        ld = "sky only" if not r.get("directional") else ",".join(f"{x:.2f}" for x in r["light_dir"])
        for name, v in sorted(
            r["runs"].items(), key=lambda kv: (kv[1]["seed"], list(VARIANTS).index(kv[1]["variant"]))
        ):
            k, s = v["key"], v["splits"]
            cells = [
                f"{_fmt(s[sp]['psnr_mask'], '.2f')} / {_fmt(s[sp]['lpips_mask'], '.4f')}" if sp in s else "-"
                for sp in ("test_frames", "test_views")
            ]
            print(
                f"| {cap} | {ld} | {name} | {_kept(k)} | {_fmt(k['found_deg'])} "
                f"| {_fmt(k['irradiance_deg'])} | {cells[0]} | {cells[1]} |"
            )


if __name__ == "__main__":
    main()
