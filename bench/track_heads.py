"""Real head videos through `meshsplat track` + train: the fitted whole head against the landmark-mesh
baseline, on held-out later frames.

    python bench/track_heads.py VIDEO_DIR [--size 256] [--iters 1500] [--work runs/bench-track]
                                [--clips a b] [--max-frames 150] [--fps 15] [--name track_heads]

For each video in VIDEO_DIR (``*.mp4 *.mov *.webm *.mkv``; sources and licences in its SOURCES.md;
bench/reports/track_heads.md says where the clips come from):

1. ``track``: the tracker writes the capture (first 80% of the frames train, the last 20% are held out:
   new expressions and poses); its landmark reprojection error and tracking time are recorded.
2. ``landmarks``: the baseline a user could build without the tracker's head: the same images and
   cameras, driven by MediaPipe's 468 landmarks as a triangle mesh per frame (the face-mesh
   tessellation; depth from MediaPipe's relative z at the fitted head's distance), masked by the filled
   hull of the landmarks.
3. Both train with the default recipe at the demo's schedule (``--iters``, densification from 1/5 to
   4/5), one after the other on the same threads; the held-out frames are rendered and scored against
   the photograph: inside the head matte, inside the landmarks' face hull, and the full image with the
   photograph composited by the head matte on white and on black (PSNR, SSIM; LPIPS in the head box
   when its weights are installed).

Prints a table, writes bench/results/<name>-<host>.json and a picture per clip (photograph | whole head |
landmark mesh | errors x4) to bench/results/<name>-<clip>.png.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from _machine import machine_info, results_path
from meshsplat.data import open_dataset
from meshsplat.data.writer import DatasetWriter
from meshsplat.metrics import lpips
from meshsplat.metrics.lpips_net import lpips_available
from meshsplat.metrics.psnr import psnr
from meshsplat.metrics.ssim import ssim
from meshsplat.metrics.subject import subject_box
from meshsplat.run_folder import load_avatar
from meshsplat.track.clip import TrackSettings
from meshsplat.track.head_capture import track_head
from meshsplat.train import DEFAULT_RECIPE, Trainer, apply_overrides, recipe_config

VIDEO_SUFFIXES = (".mp4", ".mov", ".webm", ".mkv", ".avi")
NOSE_TIP = 1  # MediaPipe landmark on the nose tip


def tessellation() -> np.ndarray:
    """Triangles ``[F,3]`` of MediaPipe's 468-point face mesh: the 3-cliques of its tessellation edges."""
    from mediapipe.python.solutions.face_mesh_connections import FACEMESH_TESSELATION

    nbr: dict[int, set[int]] = {}
    for a, b in FACEMESH_TESSELATION:
        nbr.setdefault(a, set()).add(b)
        nbr.setdefault(b, set()).add(a)
    tris = set()
    for a, na in nbr.items():
        for b in na:
            for c in na & nbr[b]:
                tris.add(tuple(sorted((a, b, c))))
    return np.array(sorted(tris), np.int64)


def landmark_meshes(landmarks: np.ndarray, K: np.ndarray, nose_depth: np.ndarray) -> np.ndarray:
    """World vertices ``[T,468,3]`` of the landmark mesh from ``landmarks [T,478,3]`` (video pixels):
    pixel (x, y) unprojected at the fitted head's nose-tip depth ``[T]`` plus MediaPipe's relative z
    (in the pixel scale of x)."""
    lm = landmarks[:, :468].astype(np.float64)
    rel = (lm[..., 2] - lm[:, NOSE_TIP : NOSE_TIP + 1, 2]) / K[0, 0]
    d = nose_depth[:, None] * (1 + rel)
    x = (lm[..., 0] - K[0, 2]) / K[0, 0] * d
    y = (lm[..., 1] - K[1, 2]) / K[1, 1] * d
    return np.stack([x, y, d], -1) * np.array([1.0, -1.0, -1.0])  # OpenCV camera -> world (+y up)


def hull_mask(points: np.ndarray, size: int) -> np.ndarray:
    """Filled convex hull ``[size,size]`` of pixel points ``[N,2]``."""
    from scipy.spatial import ConvexHull

    hull = points[ConvexHull(points).vertices]
    img = Image.new("L", (size, size), 0)
    ImageDraw.Draw(img).polygon([tuple(p) for p in hull], fill=255)
    return np.asarray(img)


def write_landmark_capture(capture: Path, out: Path) -> Path:
    """The baseline capture: ``capture``'s images and cameras, the landmark mesh, hull masks."""
    ds = open_dataset(capture)
    fit = dict(np.load(capture / "head_fit.npz"))
    man = json.loads((capture / "manifest.json").read_text())
    faces = tessellation()
    # the fitted head's nose-tip depth per frame, re-posed from the stored fit
    from meshsplat.track.ict_head import load_ict_head

    head = load_ict_head()
    identity = torch.from_numpy(np.load(capture / "head_model.npz")["neutral"]).float() - head.neutral
    f = {k: torch.from_numpy(fit[k]).float() for k in ("weights", "gaze", "rotations", "translations")}
    posed = head.pose(identity, f["weights"], f["gaze"], f["rotations"], f["translations"])
    depth = -head.landmarks(posed)[:, NOSE_TIP, 2].numpy()
    verts = landmark_meshes(fit["landmarks"], fit["K"], np.array(depth)).astype(np.float32)
    # triangles facing the camera (+z world) in the first frame
    v0 = verts[0]
    n = np.cross(v0[faces[:, 1]] - v0[faces[:, 0]], v0[faces[:, 2]] - v0[faces[:, 0]])
    faces = np.where((n[:, 2] < 0)[:, None], faces[:, [0, 2, 1]], faces)
    train = ds.split("train")
    with DatasetWriter(out, verts[train[0]], faces, overwrite=True, meta={"generator": "bench/track_heads.py"}) as w:
        for i, rec in enumerate(man["frames"]):
            cam = man["cameras"][rec["camera"]]
            w.add_camera(rec["camera"], cam["K"], cam["viewmat"], cam["width"], cam["height"])
            img = np.asarray(Image.open(capture / rec["image"]).convert("RGB"))
            lm = fit["landmarks"][i, :468, :2].astype(np.float64)
            Kc = np.asarray(cam["K"]) @ np.linalg.inv(fit["K"])  # video pixels -> crop pixels
            pts = lm @ Kc[:2, :2].T + Kc[:2, 2]
            w.add_frame(img, rec["camera"], vertices=verts[i], mask=hull_mask(pts, cam["width"]), name=rec["name"])
        for name in ds.split_names:
            w.set_split(name, ds.split(name))
    return out


def train(capture: Path, out: Path, iters: int, threads: int) -> float:
    torch.set_num_threads(threads)
    cfg = recipe_config(DEFAULT_RECIPE)
    cfg.data, cfg.out, cfg.iterations, cfg.progress = str(capture), str(out), iters, False
    cfg.model.n_init = 10_000
    cfg = apply_overrides(
        cfg,
        [
            f"strategy.refine_start_iter={iters // 5}",
            f"strategy.refine_stop_iter={iters * 4 // 5}",
            "strategy.refine_every=100",
            "strategy.reset_every=1000000",
            "strategy.max_gaussians=40000",
            "walk.every=100",
            "preview_every=1000000",
            f"checkpoint_every={iters}",
            "log_every=50",
        ],
    ).validate()
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    Trainer(cfg).train()
    return time.perf_counter() - t0


def _render(avatar, ds, i: int, bg: torch.Tensor) -> torch.Tensor:
    return avatar.render(ds.vertices(i).float(), ds.frame_camera(i), background=bg).image.clamp(0, 1)


def score(run_head: Path, run_lm: Path, cap_head: Path, cap_lm: Path, picture: Path) -> dict:
    """Metrics of both avatars on the held-out frames, and the picture."""
    ds_h, ds_l = open_dataset(cap_head), open_dataset(cap_lm)
    av = {"head": load_avatar(run_head), "landmarks": load_avatar(run_lm)}
    dss = {"head": ds_h, "landmarks": ds_l}
    use_lpips = lpips_available()
    rows: dict[str, dict[str, list[float]]] = {k: {} for k in av}
    shown = []
    test = ds_h.split("test_frames")
    for n, i in enumerate(test):
        fr_h, fr_l = ds_h[i], ds_l[i]
        gt, matte, hull = fr_h.image, fr_h.mask, fr_l.mask
        for name, avatar in av.items():
            out: dict[str, float] = {}
            for bg_name, bg in (("white", torch.ones(3)), ("black", torch.zeros(3))):
                img = _render(avatar, dss[name], i, bg)
                ref = gt * matte + bg * (1 - matte)
                out[f"psnr_full_{bg_name}"] = float(psnr(img, ref))
                if bg_name == "white":
                    out["psnr_head"] = float(psnr(img, gt, mask=(matte > 0.5).float()))
                    out["psnr_face"] = float(psnr(img, gt, mask=(hull > 0.5).float()))
                    out["ssim_full_white"] = float(ssim(img, ref))
                    box = subject_box(matte[..., 0])
                    if use_lpips and box is not None:
                        y0, y1, x0, x1 = box
                        out["lpips_head_box"] = float(lpips(img[y0:y1, x0:x1], ref[y0:y1, x0:x1]))
                    if n in (0, len(test) // 2, len(test) - 1):
                        shown.append((name, n, img, ref))
            for k, v in out.items():
                rows[name].setdefault(k, []).append(v)
    _picture(shown, picture)
    return {name: {k: float(np.mean(v)) for k, v in r.items()} for name, r in rows.items()}


def _picture(shown: list, path: Path) -> None:
    by_frame: dict[int, dict] = {}
    for name, n, img, ref in shown:
        by_frame.setdefault(n, {})[name] = img
        by_frame[n]["ref"] = ref
    rows = []
    for d in by_frame.values():
        err = [((d[k] - d["ref"]).abs() * 4).clamp(0, 1) for k in ("head", "landmarks")]
        rows.append(torch.cat([d["ref"], d["head"], d["landmarks"], *err], 1))
    grid = (torch.cat(rows, 0).numpy() * 255 + 0.5).astype(np.uint8)
    Image.fromarray(grid).save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("videos", type=Path)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--max-frames", type=int, default=150)
    ap.add_argument("--fps", type=float, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--clips", nargs="*", default=None, help="video file stems to run (default all)")
    ap.add_argument("--work", type=Path, default=Path("runs/bench-track"))
    ap.add_argument("--name", default="track_heads")
    args = ap.parse_args()
    videos = sorted(p for p in args.videos.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if args.clips:
        videos = [p for p in videos if p.stem in args.clips]
    if not videos:
        raise SystemExit(f"no videos in {args.videos}")
    path = results_path(args.name)
    results = json.loads(path.read_text()) if path.exists() else {}
    results["machine"] = machine_info()
    for video in videos:
        key = f"{video.stem}@{args.size}"
        work = args.work / key
        cap_h, cap_l = work / "capture", work / "capture_landmarks"
        settings = TrackSettings(size=args.size, fps=args.fps, max_frames=args.max_frames, overwrite=True)
        t0 = time.perf_counter()
        tr = track_head(video, cap_h, settings)
        track_s = time.perf_counter() - t0
        write_landmark_capture(cap_h, cap_l)
        t_head = train(cap_h, work / "run_head", args.iters, args.threads)
        t_lm = train(cap_l, work / "run_landmarks", args.iters, args.threads)
        metrics = score(
            work / "run_head", work / "run_landmarks", cap_h, cap_l, path.with_name(f"{args.name}-{key}.png")
        )
        results[key] = {
            "video": video.name,
            "frames": tr.frames,
            "train": tr.train,
            "test": tr.test,
            "dropped": tr.dropped,
            "landmark_error_px": tr.error_px,
            "track_seconds": track_s,
            "track_stages": tr.seconds,
            "train_seconds": {"head": t_head, "landmarks": t_lm},
            "iters": args.iters,
            "metrics": metrics,
        }
        path.write_text(json.dumps(results, indent=1))
        m = metrics
        print(
            f"{key:28s} frames {tr.frames:4d} err {tr.error_px:5.2f}px track {track_s:6.1f}s | "
            + " | ".join(
                f"{k}: head {m[k]['psnr_head']:.2f} face {m[k]['psnr_face']:.2f} full w/b "
                f"{m[k]['psnr_full_white']:.2f}/{m[k]['psnr_full_black']:.2f}"
                for k in ("head", "landmarks")
            ),
            flush=True,
        )
    print(f"saved {path}")


if __name__ == "__main__":
    main()
