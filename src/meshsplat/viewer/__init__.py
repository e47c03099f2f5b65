"""Self-contained WebGL2 viewer bundle: ``write_viewer_bundle(avatar, frames, out_dir)`` (see docs/viewer.md)."""

from meshsplat.viewer.bundle import (
    BUNDLE_VERSION,
    VERTEX_ENCODINGS,
    default_camera,
    pack_gaussians,
    page_camera,
    read_viewer_bundle,
    unpack_gaussians,
    write_viewer_bundle,
)

__all__ = [
    "write_viewer_bundle",
    "read_viewer_bundle",
    "default_camera",
    "page_camera",
    "pack_gaussians",
    "unpack_gaussians",
    "BUNDLE_VERSION",
    "VERTEX_ENCODINGS",
]
