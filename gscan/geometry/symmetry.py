"""An object's symmetries: rigid motions of its frame that map its shape (and perhaps its texture) onto itself.

- discrete: rotations `S` [4 x 4] (object frame, metres; `T_obj_obj'`), the identity not listed; a 4-fold
  rotation about z lists its 90, 180 and 270 degree turns, so the list with the identity is a group
- continuous: an axis (unit direction [3], a point on it [3], object frame, metres): every rotation about it
  (a body of revolution)

Each holds in shape alone or in shape and texture (`*_in_texture`). A pose `T_cam_obj` and `T_cam_obj @ S` show
the object alike wherever S holds in what the camera sees. The JSON form is the CLI contract's
`{"discrete": [[4x4]], "continuous": [{"axis": [3], "offset": [3]}], "holds_in": "shape"|"shape+texture"}`, with
`"in_texture": {"discrete": [bool], "continuous": [bool]}` saying which one holds in texture too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gscan.geometry.transforms import make_T, rotvec_to_R

SHAPE = "shape"
SHAPE_TEXTURE = "shape+texture"


def axis_rotation(axis: np.ndarray, offset: np.ndarray, angle_rad: float) -> np.ndarray:
    """[4 x 4] rotation by angle_rad about the axis through `offset` [3] along unit `axis` [3]."""
    R = rotvec_to_R(np.asarray(axis, dtype=np.float64) * float(angle_rad))
    c = np.asarray(offset, dtype=np.float64)
    return make_T(R, c - R @ c)


def turn_of(S: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis [3], angle in degrees in [0, 360)) of the rotation part of S [4 x 4], turning right-handed about
    the axis, whose largest component is positive (so a turn and its inverse read 90 and 270 degrees about one
    axis); the identity is 0 degrees about (0, 0, 1)."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(np.asarray(S, dtype=np.float64)[:3, :3]).as_rotvec()
    angle = float(np.linalg.norm(rv))
    if angle < 1e-9:
        return np.array([0.0, 0.0, 1.0]), 0.0
    axis = rv / angle
    if axis[int(np.argmax(np.abs(axis)))] < 0:
        axis, angle = -axis, 2 * np.pi - angle
    return axis + 0.0, float(np.degrees(angle))


@dataclass(frozen=True)
class SymmetryAxis:
    """An axis of symmetry (object frame, metres): unit `direction` [3], a `point` [3] on it, its `fold` (n for the
    turns by 360/n degrees about it, 0 for revolution) and whether those turns hold in texture too."""

    direction: np.ndarray
    point: np.ndarray
    fold: int
    in_texture: bool


@dataclass(frozen=True)
class Symmetries:
    """An object's symmetries (module docstring). Empty: none known."""

    discrete: tuple[np.ndarray, ...] = ()  # each [4 x 4]
    discrete_in_texture: tuple[bool, ...] = ()
    continuous: tuple[tuple[np.ndarray, np.ndarray], ...] = ()  # (axis [3] unit, offset [3])
    continuous_in_texture: tuple[bool, ...] = ()

    def __post_init__(self) -> None:
        if len(self.discrete) != len(self.discrete_in_texture):
            raise ValueError("one in_texture flag per discrete symmetry")
        if len(self.continuous) != len(self.continuous_in_texture):
            raise ValueError("one in_texture flag per continuous symmetry")

    def __bool__(self) -> bool:
        return bool(self.discrete or self.continuous)

    @property
    def holds_in(self) -> str | None:
        """"shape+texture" when every symmetry holds in texture too, "shape" when one holds in shape only, None
        without symmetries."""
        if not self:
            return None
        return SHAPE_TEXTURE if all(self.discrete_in_texture + self.continuous_in_texture) else SHAPE

    def in_texture(self) -> Symmetries:
        """The symmetries that hold in shape and texture (those under which two poses look the same)."""
        d = [S for S, t in zip(self.discrete, self.discrete_in_texture, strict=True) if t]
        c = [a for a, t in zip(self.continuous, self.continuous_in_texture, strict=True) if t]
        return Symmetries(tuple(d), (True,) * len(d), tuple(c), (True,) * len(c))

    def elements(self, steps: int = 36) -> list[np.ndarray]:
        """The group's elements [4 x 4], the identity first: each continuous symmetry sampled every 360/steps
        degrees, combined with each discrete one."""
        out = [np.eye(4)]
        for axis, offset in self.continuous:
            out = [axis_rotation(axis, offset, 2 * np.pi * k / steps) @ S for k in range(steps) for S in out]
        base = list(out)
        for D in self.discrete:
            out += [S @ D for S in base]
        return out

    def axes(self) -> list[SymmetryAxis]:
        """The axes of symmetry: each axis of revolution, then each axis the discrete turns are about (turns about
        one axis grouped: its fold from the smallest of them; in texture when all of them are)."""
        out = [SymmetryAxis(np.asarray(a, float), np.asarray(o, float), 0, t)
               for (a, o), t in zip(self.continuous, self.continuous_in_texture, strict=True)]
        groups: list[tuple[np.ndarray, np.ndarray, list[float], list[bool]]] = []
        for S, t in zip(self.discrete, self.discrete_in_texture, strict=True):
            axis, angle = turn_of(S)
            S = np.asarray(S, dtype=np.float64)
            point = np.linalg.lstsq(np.eye(3) - S[:3, :3], S[:3, 3], rcond=1e-6)[0]  # fixed points: the axis
            point = point - axis * float(point @ axis)
            for a, p, angles, flags in groups:
                if abs(float(a @ axis)) > 1 - 1e-6 and np.linalg.norm(p - point) < 1e-6:
                    angles.append(angle)
                    flags.append(t)
                    break
            else:
                groups.append((axis, point, [angle], [t]))
        for a, p, angles, flags in groups:
            step = min(min(x, 360.0 - x) for x in angles)
            out.append(SymmetryAxis(a, p, max(2, int(round(360.0 / step))), all(flags)))
        return out

    def to_json(self) -> dict:
        """The CLI contract's object (module docstring)."""
        return {"discrete": [np.asarray(S, dtype=float).tolist() for S in self.discrete],
                "continuous": [{"axis": np.asarray(a, dtype=float).tolist(),
                                "offset": np.asarray(o, dtype=float).tolist()} for a, o in self.continuous],
                "holds_in": self.holds_in,
                "in_texture": {"discrete": list(self.discrete_in_texture),
                               "continuous": list(self.continuous_in_texture)}}

    @classmethod
    def from_json(cls, d: dict | None) -> Symmetries:
        """The inverse of `to_json` (None or {}: no symmetries). Raises ValueError for a malformed object."""
        if not d:
            return cls()
        try:
            disc = tuple(np.asarray(S, dtype=np.float64).reshape(4, 4) for S in d.get("discrete", []))
            cont = tuple((np.asarray(c["axis"], dtype=np.float64).reshape(3),
                          np.asarray(c["offset"], dtype=np.float64).reshape(3)) for c in d.get("continuous", []))
            flags = d.get("in_texture") or {}
            all_tex = d.get("holds_in") == SHAPE_TEXTURE
            dt = tuple(bool(x) for x in flags.get("discrete", [all_tex] * len(disc)))
            ct = tuple(bool(x) for x in flags.get("continuous", [all_tex] * len(cont)))
            return cls(disc, dt, cont, ct)
        except (KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"malformed symmetries: {e}") from None
