"""Component ``shading``: pose-dependent lighting (``meshsplat.gaussians.shading``).

The SH colour becomes an albedo, times a learned 2nd-order SH irradiance of the Gaussian's posed normal; with
``occlusion`` the posed mesh also casts shadows of learned lights (``key``: one key light found in training). The
lighting has its own Adam at ``lr``. The avatar's state carries the lighting itself (``Avatar.state_dict``), so
checkpoints, exports and the player read it from one place; this component's checkpoint state is its optimizer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from meshsplat.errors import MeshsplatError
from meshsplat.gaussians.shading import OCCLUSION_MODES, SHADING_NORMALS, SPECULAR_MODES, Shading
from meshsplat.train.components.base import Component

__all__ = ["ShadingConfig", "ShadingComponent"]


@dataclass
class ShadingConfig:
    """Pose-dependent shading; off: one colour per Gaussian (the paper)."""

    enabled: bool = False
    normal: str = "phong"  # "phong": the embedding's interpolated normal | "axis": shortest Gaussian axis
    # shadows from the posed driving mesh: "none" | "directions": learned lights from `directions` fixed directions,
    # each Gaussian's visibility on a grid^2 depth map per direction | "key": the same, then one key light found among
    # them in stages of `key_iter` iterations (Shading.align_key), the rest folded into the SH2 irradiance
    occlusion: str = "key"
    directions: int = 16
    grid: int = 96  # cells per side of each shadow map
    key_iter: int = 300
    key_soft: float = 12.0  # "key": the light's angular radius (degrees), a soft area-light shadow; 0: hard
    # "key": the first stage starts from the learned irradiance's own direction (Shading.key_seed); false: from the
    # strongest candidates' estimate
    key_seed: bool = False
    # "key": training frames (spread over the training split) rendered once the key is aligned, to keep it only if
    # its shadow lowers their L1 error (else it is folded into the SH2 irradiance, occlusion none from then on); 0: no
    # check
    key_check_frames: int = 0
    key_check_gain: float = 0.002  # the share of the check frames' L1 error the key's shadow must take away to stay
    # "key": once aligned and at the last iteration, the key stays only within this many degrees of the learned
    # irradiance's own direction (Shading.key_seed); farther, its shadows fit the training frames from a light that
    # is not there, and it is folded into the SH2 irradiance as the check does; 0: no such test
    key_agree_deg: float = 0.0
    # "key": once aligned and at the last iteration, a key farther than this many degrees from the learned
    # irradiance's direction (and not dropped by key_agree_deg) moves there (Shading.move_key: the unshadowed
    # irradiance kept, only the shadow moves); 0: it stays where the search put it
    key_snap_deg: float = 0.0
    # "sh2": an added (not albedo-multiplied) SH2 term of the normal, zero at the start (a glossy highlight)
    specular: str = "none"
    lr: float = 5e-2  # the lighting's Adam (times sqrt(batch_size))

    def checks(self) -> list[tuple[bool, str]]:
        return [
            (self.normal in SHADING_NORMALS, f"shading.normal: {'|'.join(SHADING_NORMALS)}"),
            (self.occlusion in OCCLUSION_MODES, f"shading.occlusion: {'|'.join(OCCLUSION_MODES)}"),
            (self.specular in SPECULAR_MODES, f"shading.specular: {'|'.join(SPECULAR_MODES)}"),
            (1 <= self.directions <= 256, "shading.directions must be in 1..256"),
            (8 <= self.grid <= 1024, "shading.grid must be in 8..1024"),
            (self.key_iter >= 1, "shading.key_iter must be >= 1"),
            (0.0 <= self.key_soft <= 45.0, "shading.key_soft must be in 0..45 (degrees)"),
            (0 <= self.key_check_frames <= 64, "shading.key_check_frames must be in 0..64"),
            (0.0 <= self.key_check_gain < 1.0, "shading.key_check_gain must be in [0, 1)"),
            (0.0 <= self.key_agree_deg <= 180.0, "shading.key_agree_deg must be in 0..180 (degrees; 0: off)"),
            (0.0 <= self.key_snap_deg <= 180.0, "shading.key_snap_deg must be in 0..180 (degrees; 0: off)"),
            (self.lr > 0, "shading.lr must be > 0"),
        ]


class ShadingComponent(Component):
    name = "shading"
    cfg: ShadingConfig

    def __init__(self, cfg: ShadingConfig, state: Any) -> None:
        super().__init__(cfg, state)
        self.shading: Shading | None = None
        self.optimizer: torch.optim.Adam | None = None
        # what the key light did (checkpointed): the seed and strongest estimate, the check errors, kept
        self.key_log: dict[str, Any] = {}

    def start(self) -> None:
        c = self.cfg
        self._set(
            Shading(
                normal=c.normal,
                device=self.state.device,
                occlusion=c.occlusion,
                directions=c.directions,
                grid=c.grid,
                specular=c.specular,
                key_soft=c.key_soft if c.occlusion == "key" else 0.0,
            )
        )

    def _set(self, shading: Shading) -> None:
        """Make ``shading``'s tensors trainable leaves on the device, with a new Adam over them."""
        dev = self.state.device
        shading.coeffs = torch.nn.Parameter(shading.coeffs.detach().clone().to(dev))
        if shading.light is not None:
            shading.light = torch.nn.Parameter(shading.light.detach().clone().to(dev))
        if shading.specular is not None:
            shading.specular = torch.nn.Parameter(shading.specular.detach().clone().to(dev))
        self.shading = shading
        self.optimizer = torch.optim.Adam(
            shading.parameters(), lr=self.cfg.lr * self.state.lr_factor, eps=self.state.eps
        )

    def parameters(self) -> list[torch.Tensor]:
        return [] if self.shading is None else self.shading.parameters()

    def after_step(self, it: int, rows: list[int]) -> None:
        assert self.optimizer is not None and self.shading is not None
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.shading.project()
        self._align_key(it)

    def _align_key(self, it: int) -> None:
        """``occlusion=key``: the next stage every ``key_iter`` iterations, all that are left at the last
        iteration (a short run ends with one key light too). ``key_seed``: the first stage starts from
        ``Shading.key_seed``; once aligned, and again at the last iteration, the key is dropped
        (``Shading.drop_key``) when it is farther than ``key_agree_deg`` from the learned irradiance's direction,
        and moved to that direction (``Shading.move_key``) when farther than ``key_snap_deg``; once aligned
        (``key_check_frames``) also unless its shadow lowers the check frames' error by ``key_check_gain``."""
        sh, every = self.shading, self.cfg.key_iter
        if sh is None or sh.occlusion != "key":
            return
        if sh.key_aligned:  # once more at the end: the irradiance the key was tested against had not settled
            if it == self.state.iterations and self._tests_key() and self._agree_key(sh, "end") != "kept":
                self._set(sh)
            return
        stage = sh.key_stage
        while not sh.key_aligned and (it >= every * (sh.key_stage + 1) or it == self.state.iterations):
            if sh.key_stage == 0 and self.cfg.key_seed:
                sh.align_key(start=self._seed(sh))
            else:
                sh.align_key()
        if sh.key_aligned and self._tests_key():
            self._agree_key(sh, "aligned")
        if sh.key_aligned and sh.occlusion == "key" and self.cfg.key_check_frames:
            self._check_key(sh)
        if sh.key_stage != stage or sh.occlusion != "key":  # new tensors: a new optimizer
            self._set(sh)

    def _check_frames(self) -> list[int]:
        ids, k = self.state.train_ids, min(self.cfg.key_check_frames, len(self.state.train_ids))
        return [ids[(2 * j + 1) * len(ids) // (2 * k)] for j in range(k)]  # spread evenly, none at the ends

    @torch.no_grad()
    def _error(self, trial: Shading) -> float:
        """Mean L1 error of the check frames rendered with ``trial`` as the avatar's lighting (the avatar and the
        generators untouched)."""
        own = self.shading
        self.shading = trial
        try:
            frames = self._check_frames()
            return sum(float(self.state.training_error(i)) for i in frames) / len(frames)
        finally:
            self.shading = own

    def _seed(self, sh: Shading) -> torch.Tensor:
        """The first stage's start: the learned irradiance's own direction (logged beside the strongest
        candidates' estimate, the start without ``key_seed``)."""
        seed = sh.key_seed()
        self.key_log["seed"], self.key_log["strongest"] = seed.tolist(), sh.key_estimate().tolist()
        return seed

    def _tests_key(self) -> bool:
        """Whether the aligned key is tested against the learned irradiance (``key_agree_deg`` or ``key_snap_deg``)."""
        return bool(self.cfg.key_agree_deg or self.cfg.key_snap_deg)

    def _agree_key(self, sh: Shading, when: str) -> str:
        """Drop the aligned key when its direction is more than ``key_agree_deg`` from the learned irradiance's,
        move it there when more than ``key_snap_deg``; ``when`` ("aligned" | "end") names the test in
        ``key_log``. What became of the key: "kept" | "moved" | "dropped"."""
        assert sh.directions is not None
        key, irradiance = sh.directions[0].detach(), sh.key_seed()
        cos = float(key @ irradiance / (key.norm() * irradiance.norm()))
        angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
        agrees = not self.cfg.key_agree_deg or angle <= self.cfg.key_agree_deg
        fate = (
            "dropped" if not agrees else "moved" if self.cfg.key_snap_deg and angle > self.cfg.key_snap_deg else "kept"
        )
        self.key_log[f"agree_{when}"] = {
            "irradiance": irradiance.tolist(),
            "angle_deg": angle,
            "agrees": agrees,
            "fate": fate,
        }
        if fate == "dropped":
            sh.drop_key()
        elif fate == "moved":
            self.key_log[f"agree_{when}"]["from"] = key.tolist()
            sh.move_key(irradiance)
        return fate

    def _check_key(self, sh: Shading) -> None:
        off = sh.to(self.state.device)
        off.drop_key()
        errors = {"key": self._error(sh), "off": self._error(off)}
        self.key_log["check_errors"] = errors
        self.key_log["kept"] = kept = errors["key"] < errors["off"] * (1.0 - self.cfg.key_check_gain)
        if not kept:
            sh.drop_key()

    def state_dict(self) -> Any:
        if self.optimizer is None:
            return None
        return {"optimizer": self.optimizer.state_dict(), "key_log": dict(self.key_log)}

    def load_state_dict(self, state: Any, checkpoint: dict[str, Any]) -> None:
        shading = Shading.from_state_dict(checkpoint["avatar"].get("shading"), self.state.device)
        dropped = shading is not None and shading.dropped_key is not None and self.cfg.occlusion == "key"
        if (
            shading is None
            or (shading.occlusion != self.cfg.occlusion and not dropped)
            or shading.specular_mode != self.cfg.specular
        ):
            raise MeshsplatError(
                "checkpoint: its avatar's lighting does not match the shading section of the configuration; "
                "resume with the run's own config.json or start a new run"
            )
        self._set(shading)
        if state:
            assert self.optimizer is not None
            self.optimizer.load_state_dict(state["optimizer"])
            self.key_log = dict(state.get("key_log") or {})
