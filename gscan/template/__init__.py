"""Template storage: one SQLite database per object (`OBJ.gscan`) with its views, keypoints, registration edges,
mesh, cloud and grasps, and the in-memory `Template` the estimator loads.

- db: `TemplateDB` (`create`, `open`), `open_template`, `SCHEMA_VERSION`
- records: `View`, `Edge`, `TemplateSummary`, `Template` (keypoints are `gscan.features.Features`, the mesh
  `gscan.geometry.MeshData`)
- reports: `template_info -> TemplateInfo`, `template_poses -> TemplatePoses`, `template_grasps -> GraspList`
  (what `gscan info`, `poses` and `grasp list` print: their `to_json()`), `store_grasp`
"""
from __future__ import annotations

from gscan.registration.edge import Edge
from gscan.template.db import SCHEMA_VERSION, TemplateDB, open_template, unregistered_names
from gscan.template.records import Template, TemplateSummary, View

__all__ = ["SCHEMA_VERSION", "Edge", "Template", "TemplateDB", "TemplateSummary", "View", "open_template",
           "unregistered_names"]
