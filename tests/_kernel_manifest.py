"""Records which compiled CPU kernels training calls, with which argument types: the manifest
``src/meshsplat/train/cpu_kernels.json`` that ``train.cpu_kernels.compile_ahead`` compiles from after an install.

    python tests/_kernel_manifest.py      # rewrite the manifest (about a minute: an empty numba cache, to time it)

Rewrite it when a kernel's arguments change; ``tests/train/test_cpu_kernels.py`` fails until then. The recording is
the tiny demo's training (the default recipe) on 2 threads, every step, in a fresh process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
THREADS = 2


def record_training(data: Path, steps: int | None = None) -> list[dict]:
    """In this process: the tiny demo's trainer on ``data``, ``steps`` steps (default: all of them) on
    ``THREADS`` threads, recorded by ``_numba_ahead.record``."""
    import torch

    from meshsplat._numba_ahead import record
    from meshsplat.demo import PRESETS, demo_train_config
    from meshsplat.train import Trainer

    torch.set_num_threads(THREADS)
    cfg = demo_train_config(data, Path(tempfile.mkdtemp()), PRESETS["tiny"], [], progress=False)
    trainer = Trainer(cfg)
    n = cfg.iterations if steps is None else steps
    return record(lambda: [trainer.step() for _ in range(n)])


def tiny_data(folder: Path) -> Path:
    from meshsplat.demo import PRESETS, _generate

    return _generate(folder / "data", PRESETS["tiny"], progress=False)


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":  # the recording itself, in a fresh process
        print(json.dumps(record_training(Path(sys.argv[2]))))
        return 0
    sys.path.insert(0, str(ROOT / "src"))
    tmp = Path(tempfile.mkdtemp(prefix="kernel_manifest_"))
    data = tiny_data(tmp)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "cache"), PYTHONPATH=str(ROOT / "src"))
    out = subprocess.run([sys.executable, __file__, "--child", str(data)], env=env, capture_output=True, text=True)
    if out.returncode != 0:
        sys.stderr.write(out.stderr)
        return 1
    entries = json.loads(out.stdout.strip().splitlines()[-1])
    path = ROOT / "src" / "meshsplat" / "train" / "cpu_kernels.json"
    text = json.dumps({"threads": THREADS, "entries": entries}, indent=1)
    path.write_text(text + "\n")
    total = sum(e["seconds"] for e in entries)
    print(f"wrote {path.relative_to(ROOT)}: {len(entries)} kernels, {total:.1f} s of CPU to compile them here")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
