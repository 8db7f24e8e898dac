"""Synthetic RGB-D renderer with exact ground truth (open3d RaycastingScene on the CPU).

Public API (import from `gscan.synth`):
- meshes: `TexturedMesh`, `load_textured_mesh`, `plain_mesh`, `box_mesh`, `cylinder_mesh`, `save_textured_mesh`
- textures: `procedural_box_texture`, `table_texture`
- rendering: `SynthScene`, `RenderedFrame`, `Gloss`, `DEFAULT_INTRINSICS`, `DepthNoise`, `apply_depth_noise`
- capture: `orbit_poses`, `turntable_poses`, `rest_on_table`, `view_on_table`, `place_distractors`,
  `default_distance`, `write_capture`, `render_capture`

Names are imported on first use (PEP 562): a module that needs the meshes alone (`gscan.synth.mesh`, read by the
symmetry check that every scan's configuration names) does not load open3d, which only the renderer needs.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports

_MODULE_NAMES = {
    "gscan.synth.capture": ("default_distance", "footprint_radius", "orbit_poses", "place_distractors",
                            "render_capture", "rest_on_table", "turntable_poses", "view_on_table", "write_capture"),
    "gscan.synth.mesh": ("TexturedMesh", "box_mesh", "cylinder_mesh", "load_textured_mesh", "plain_mesh",
                         "sample_bilinear", "sample_mip", "save_textured_mesh", "texture_pyramid"),
    "gscan.synth.noise": ("DepthNoise", "apply_depth_noise", "depth_sigma"),
    "gscan.synth.render": ("DEFAULT_INTRINSICS", "Gloss", "RenderedFrame", "SynthScene"),
    "gscan.synth.textures": ("procedural_box_texture", "table_texture"),
}
_EXPORTS = {name: module for module, names in _MODULE_NAMES.items() for name in names}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:
    from gscan.synth.capture import (
                                     default_distance,
                                     footprint_radius,
                                     orbit_poses,
                                     place_distractors,
                                     render_capture,
                                     rest_on_table,
                                     turntable_poses,
                                     view_on_table,
                                     write_capture,
    )
    from gscan.synth.mesh import (
                                     TexturedMesh,
                                     box_mesh,
                                     cylinder_mesh,
                                     load_textured_mesh,
                                     plain_mesh,
                                     sample_bilinear,
                                     sample_mip,
                                     save_textured_mesh,
                                     texture_pyramid,
    )
    from gscan.synth.noise import DepthNoise, apply_depth_noise, depth_sigma
    from gscan.synth.render import DEFAULT_INTRINSICS, Gloss, RenderedFrame, SynthScene
    from gscan.synth.textures import procedural_box_texture, table_texture

__all__ = [
    "DEFAULT_INTRINSICS", "DepthNoise", "Gloss", "RenderedFrame", "SynthScene", "TexturedMesh", "apply_depth_noise",
    "box_mesh", "cylinder_mesh", "default_distance", "depth_sigma", "footprint_radius", "load_textured_mesh",
    "orbit_poses", "place_distractors", "plain_mesh", "procedural_box_texture", "render_capture", "rest_on_table",
    "sample_bilinear", "sample_mip", "save_textured_mesh", "table_texture", "texture_pyramid", "turntable_poses",
    "view_on_table", "write_capture",
]
