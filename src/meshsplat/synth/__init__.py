"""Ground-truth generator: animated textured meshes rendered into native-format datasets."""

from meshsplat.synth.contact import contact_sheet
from meshsplat.synth.generate import RIGS, SynthSpec, render_view, synthesize
from meshsplat.synth.raster import Fragments, rasterize_triangles
from meshsplat.synth.sources import load_source

__all__ = [
    "synthesize",
    "SynthSpec",
    "render_view",
    "RIGS",
    "rasterize_triangles",
    "Fragments",
    "load_source",
    "contact_sheet",
]
