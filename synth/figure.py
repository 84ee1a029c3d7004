"""An articulated human figure made of Gaussians: a bone hierarchy, textured limbs, forward kinematics.

World frame: z up, metres; the figure stands on z = 0 facing -y. Each bone's geometry is built in
its own frame, whose origin is the joint it hangs from and whose -z axis runs down the limb at rest
(arms hanging, legs straight). A pose is a local rotation per bone (relative to its parent, about
the joint) plus the root's position; ``Figure.posed`` moves every Gaussian with its bone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.geometry import rotmat_to_quat
from edmcgs.synth.cloud import Cloud, pose_parts
from edmcgs.synth.primitives import box, capsule, checker, ellipsoid, solid, stripes

SKIN = (0.85, 0.62, 0.48)
SHOE = (0.12, 0.1, 0.1)
ROOT_HEIGHT = 0.98
"""Height of the pelvis joint when the figure stands straight."""


@dataclass(frozen=True)
class Bone:
    name: str
    parent: str | None
    offset: tuple[float, float, float]
    """The bone's joint in its parent's frame at rest (in the world for the root)."""


BONES = (
    Bone("pelvis", None, (0.0, 0.0, ROOT_HEIGHT)),
    Bone("torso", "pelvis", (0.0, 0.0, 0.05)),
    Bone("head", "torso", (0.0, 0.0, 0.6)),
    Bone("upper_arm_l", "torso", (0.23, 0.0, 0.5)),
    Bone("forearm_l", "upper_arm_l", (0.0, 0.0, -0.3)),
    Bone("upper_arm_r", "torso", (-0.23, 0.0, 0.5)),
    Bone("forearm_r", "upper_arm_r", (0.0, 0.0, -0.3)),
    Bone("thigh_l", "pelvis", (0.1, 0.0, -0.04)),
    Bone("shin_l", "thigh_l", (0.0, 0.0, -0.45)),
    Bone("thigh_r", "pelvis", (-0.1, 0.0, -0.04)),
    Bone("shin_r", "thigh_r", (0.0, 0.0, -0.45)),
)
BONE_INDEX = {b.name: i for i, b in enumerate(BONES)}


def _bone_geometry(name: str, spacing: float, palette: dict) -> Cloud:
    """The Gaussians of one bone, in its frame."""
    arm = stripes(2, 0.1, palette["arm_a"], palette["arm_b"])
    leg = stripes(2, 0.12, palette["leg_a"], palette["leg_b"])
    if name == "pelvis":
        return ellipsoid((0, 0, 0), (0.17, 0.11, 0.1), spacing, solid(palette["leg_b"]))
    if name == "torso":
        return ellipsoid((0, 0, 0.28), (0.19, 0.12, 0.31), spacing, checker(0.18, palette["shirt_a"],
                                                                            palette["shirt_b"]))
    if name == "head":
        skin, hair = np.asarray(SKIN), np.asarray(palette["hair"])

        def face(p):  # hair over the crown and the back of the head, skin in front
            return np.where(((p[:, 2] > 0.19) | (p[:, 1] > 0.03))[:, None], hair, skin)
        neck = capsule(0.06, 0.045, spacing, solid(SKIN)).translated((0, 0, 0.06))
        return Cloud.concat([neck, ellipsoid((0, 0, 0.15), (0.1, 0.11, 0.12), spacing, face)])
    if name.startswith("upper_arm"):
        return capsule(0.3, 0.05, spacing, arm)
    if name.startswith("forearm"):
        return Cloud.concat([capsule(0.26, 0.042, spacing, arm),
                             ellipsoid((0, 0, -0.31), (0.045, 0.03, 0.06), spacing, solid(SKIN))])
    if name.startswith("thigh"):
        return capsule(0.45, 0.075, spacing, leg)
    if name.startswith("shin"):
        return Cloud.concat([capsule(0.42, 0.058, spacing, leg),
                             box((0, -0.05, -0.47), (0.1, 0.22, 0.07), spacing, solid(SHOE))])
    raise KeyError(name)


class Figure:
    """The figure's Gaussians bound to its bones; ``posed`` applies a pose."""

    def __init__(self, spacing: float, palette: dict) -> None:
        parts = [_bone_geometry(b.name, spacing, palette) for b in BONES]
        self.rest = Cloud.concat(parts)
        """Gaussians in their bones' frames."""
        self.bone = np.concatenate([np.full(len(c), i) for i, c in enumerate(parts)])
        """int [N]: the bone of each Gaussian."""
        self._parent = [BONE_INDEX[b.parent] if b.parent else -1 for b in BONES]
        self._offset = np.array([b.offset for b in BONES], dtype=np.float64)

    def bone_transforms(self, local: dict[str, np.ndarray],
                        root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics: world (R [B, 3, 3], T [B, 3]) of each bone's frame.

        local: bone name -> 3x3 rotation relative to its parent (missing: identity); root: the pelvis
        joint's world position [3].
        """
        n = len(BONES)
        rot, trans = np.empty((n, 3, 3)), np.empty((n, 3))
        for i, parent in enumerate(self._parent):  # BONES lists parents before children
            r_local = local.get(BONES[i].name, np.eye(3))
            if parent < 0:
                rot[i], trans[i] = r_local, root
            else:
                rot[i] = rot[parent] @ r_local
                trans[i] = trans[parent] + rot[parent] @ self._offset[i]
        return rot, trans

    def posed(self, local: dict[str, np.ndarray], root) -> Cloud:
        rot, trans = self.bone_transforms(local, np.asarray(root, dtype=np.float64))
        return pose_parts(self.rest, self.bone, rot, rotmat_to_quat(rot), trans)
