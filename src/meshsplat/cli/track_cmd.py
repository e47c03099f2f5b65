"""Track a head or a body in a video and write a capture to train on (needs the [track] extra).

One person's head, one camera: a phone or webcam clip of a face talking and turning a little. Every
frame gets MediaPipe's 478 face landmarks; the bundled ICT head (with mouth interior, teeth and eyes)
is fitted to them (identity once, expressions, gaze, head pose); each frame is cut to a square around
the head with a matte of head, hair and neck. The capture trains with `meshsplat train CAPTURE`; its
first --train-fraction of frames train, the later ones are held out.

Good clips: 10-60 s, the face lit evenly and in view, expressions and a little head turning.
Frames without a face are left out (named); a clip with a scene cut, or with a face in fewer than
10 frames, is refused.

Bodies (--subject body): one person, the whole body in view, turning and moving. Every frame gets
MediaPipe Pose's 33 landmarks and a person matte; the Anny body model (pip-installed, CC0 assets) is
fitted (shape once, pose and position per frame) and posed per frame; each frame is cut to a square
around the body. Pose refinement is on when training; `render RUN --animation motion aist_demo` dances.

Examples:
  meshsplat track me.mp4 --out captures/me
  meshsplat track dance.mp4 --out captures/dance --subject body --fps 10
  meshsplat track me.mov --out captures/me --size 256 --fps 15 --start 2 --seconds 20
  meshsplat train captures/me --out runs/me
"""

from __future__ import annotations

import argparse
import sys

from meshsplat.track.body_capture import track_body
from meshsplat.track.clip import TrackSettings
from meshsplat.track.head_capture import track_head

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("video", metavar="VIDEO", help="video file (MP4, MOV, WebM, MKV)")
    parser.add_argument("--out", required=True, help="capture folder to write (new or empty)")
    parser.add_argument(
        "--subject",
        choices=["head", "body"],
        default="head",
        help="what to track: a head or a whole body (default head)",
    )
    parser.add_argument("--size", type=int, default=512, help="capture image size in pixels (square; default 512)")
    parser.add_argument("--fps", type=float, default=None, help="resample the video to this frame rate")
    parser.add_argument("--start", type=float, default=0.0, help="first second of the video to use (default 0)")
    parser.add_argument("--seconds", type=float, default=None, help="how many seconds to use (default: to the end)")
    parser.add_argument("--max-frames", type=int, default=None, help="use at most this many frames")
    parser.add_argument(
        "--train-fraction", type=float, default=0.8, help="the first part of the frames that trains (default 0.8)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace the capture in a non-empty --out folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _progress_bar(enabled: bool):
    if not enabled:
        return None, lambda: None
    from tqdm import tqdm

    bars: dict[str, tqdm] = {}

    def tick(stage: str, done: int, total: int) -> None:
        bar = bars.get(stage)
        if bar is None:
            for b in bars.values():
                b.close()
            bar = bars[stage] = tqdm(total=total, desc=stage, unit="frame", ncols=78, file=sys.stderr, leave=False)
        if done > bar.total:
            bar.total = done
        bar.update(done - bar.n)

    def close() -> None:
        for b in bars.values():
            b.close()

    return tick, close


def run(args: argparse.Namespace) -> int:
    settings = TrackSettings(
        size=args.size,
        fps=args.fps,
        start=args.start,
        seconds=args.seconds,
        max_frames=args.max_frames,
        train_fraction=args.train_fraction,
        overwrite=args.overwrite,
    )
    tick, close = _progress_bar(not args.no_progress)
    track = track_body if args.subject == "body" else track_head
    try:
        res = track(args.video, args.out, settings, progress=tick)
    finally:
        close()
    for note in res.notes:
        print(f"note: {note}", file=sys.stderr)
    t = res.seconds
    per = 1000 * (t.get("landmarks", 0) + t.get("frames", 0)) / max(res.frames, 1)
    what = "keypoint" if args.subject == "body" else "landmark"
    print(
        f"tracked {res.frames} frames ({res.train} train, {res.test} held out); {what} error {res.error_px:.2f} px; "
        f"landmarks {t.get('landmarks', 0):.1f} s, fit {t.get('fit', 0):.1f} s, frames {t.get('frames', 0):.1f} s "
        f"({per:.0f} ms a frame)"
    )
    print(f"capture written to {res.capture}; next: meshsplat train {res.capture} --out runs/{res.capture.name}")
    return 0
