"""Gaussian parameters embedded on a mesh, their composition in a pose, and the Avatar object."""

from meshsplat.gaussians.avatar import Avatar, AvatarRender
from meshsplat.gaussians.compose import ComposedGaussians, compose, effective_uv, eval_sh
from meshsplat.gaussians.params import (
    EMBEDDING_STATE_KEYS,
    PARAM_KEYS,
    SH_C0,
    check_params,
    init_params,
    knn_scales,
    make_params,
    num_gaussians,
    num_sh_rest,
    rgb_to_sh0,
    sh0_to_rgb,
    sh_degree_of,
)

__all__ = [
    "Avatar",
    "AvatarRender",
    "ComposedGaussians",
    "compose",
    "effective_uv",
    "eval_sh",
    "PARAM_KEYS",
    "EMBEDDING_STATE_KEYS",
    "SH_C0",
    "check_params",
    "init_params",
    "knn_scales",
    "make_params",
    "num_gaussians",
    "num_sh_rest",
    "rgb_to_sh0",
    "sh0_to_rgb",
    "sh_degree_of",
]
