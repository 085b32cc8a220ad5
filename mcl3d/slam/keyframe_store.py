"""The host side of SLAM's bounded keyframe store: which scan made each keyframe, the cloud in
each slot, the poses of keyframes that were dropped, and which slot a new keyframe reuses
once all `keyframes.capacity` slots are used.

A keyframe is known by its number (the order keyframes were made in); the particles hold its
pose in a slot (SlamParticles). When the slots are full, a new keyframe takes the slot of the
most redundant kept one: the keyframe with an older keyframe closest to it, facing the same
way. A place seen again thus keeps the keyframe it was first mapped with (the newest few
stay for local tracking until they age out), new ground thins the densest stretch, and the
first keyframe, which fixes the map's frame, stays: memory is bounded while the map keeps
covering what it can hold and loops to it stay closable however long the run. A dropped
keyframe's pose is frozen as the representative particle held it then: scans made before
the next keyframe keep hanging off it in the trajectory.
"""

from __future__ import annotations

import numpy as np


def slot_to_reuse(T_slots: np.ndarray, seq: np.ndarray, protected: set[int],
                  min_facing_cos: float) -> int:
    """The slot whose keyframe has an older one nearest to it, counting only older ones whose
    lidar +x axis is within acos(`min_facing_cos`) of its own (they see the same side of the
    place); ties go to the newer keyframe. `T_slots` (K, 4, 4) are one particle's keyframe
    poses by slot, `seq` (K,) their numbers; slots in `protected` are never chosen unless all
    are."""
    K = len(seq)
    pos = T_slots[:, :3, 3]
    fwd = T_slots[:, :3, 0]
    dist = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=2)
    same_side = fwd @ fwd.T >= min_facing_cos
    older = seq[None, :] < seq[:, None]
    nearest_older = np.where(same_side & older, dist, np.inf).min(axis=1)
    allowed = np.array([k not in protected for k in range(K)])
    if not allowed.any():
        allowed[:] = True
    candidates = np.flatnonzero(allowed)
    best = np.lexsort((-seq[candidates], nearest_older[candidates]))[0]
    return int(candidates[best])


class KeyframeBook:
    """Per keyframe number the scan that made it and the odometry's drift variance then, per
    slot the keyframe's cloud (lidar frame), and the frozen poses of dropped keyframes."""

    def __init__(self) -> None:
        self.frames: list[int] = []  # scan index of keyframe number s
        # the prediction's rotational, translational and elevator variance summed up to number s
        self.drift_variance: list[tuple[float, float, float]] = []
        self.clouds: list[np.ndarray] = []  # by slot
        self.retired: dict[int, np.ndarray] = {}  # number -> pose when it was dropped

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, slot: int, frame_index: int, cloud: np.ndarray,
            drift_variance: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """Keyframe number len(self) made from scan `frame_index`, in `slot`, when the
        prediction's rotational and translational variance and the elevator's vertical random
        walk summed along the path were `drift_variance` (rad², m², m²; see loop_bridge)."""
        self.frames.append(frame_index)
        self.drift_variance.append(drift_variance)
        if slot == len(self.clouds):
            self.clouds.append(cloud)
        else:
            self.clouds[slot] = cloud

    def retire(self, number: int, T_world_keyframe: np.ndarray) -> None:
        self.retired[number] = T_world_keyframe.copy()

    def poses_by_number(self, T_slots: np.ndarray, seq: np.ndarray) -> np.ndarray:
        """(len(self), 4, 4): every keyframe ever made, the live ones from `T_slots` (one
        particle's poses by slot, `seq` their numbers), the dropped ones as frozen."""
        out = np.tile(np.eye(4), (len(self.frames), 1, 1))
        for number, T in self.retired.items():
            out[number] = T
        out[seq[:len(T_slots)]] = T_slots
        return out
