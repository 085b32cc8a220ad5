"""The odometry's typed config section (`odometry:` in a config file; SLAM embeds it)."""

from __future__ import annotations

from pydantic import Field, model_validator

from mcl3d.core.config import Section


class OdometryConfig(Section):
    voxel_size_m: float = Field(0.25, gt=0, description="downsampling voxel edge (m)")
    map_voxel_size_m: float | None = Field(None, gt=0, description="finest keyframe voxel "
                                           "map edge (m), a second level twice as coarse; "
                                           "None: GLIM's rule from the first scan's median "
                                           "range, 0.25 m (<= 5 m) to 0.5 m (>= 20 m)")
    map_levels: int = Field(2, ge=1, le=3, description="voxel map resolutions per keyframe")
    k_neighbors: int = Field(10, ge=5, description="neighbours for point covariances")
    min_range_m: float = Field(0.5, ge=0, description="drop points closer than this (m)")
    max_range_m: float = Field(100.0, gt=0, description="drop points farther than this (m)")
    keyframe_overlap: float = Field(0.7, gt=0, le=1, description="new keyframe when the "
                                    "scan's overlap with the keyframes drops below this")
    max_keyframes: int = Field(10, ge=1, le=64, description="keyframes in the local map "
                               "(oldest evicted; the overlap test lists them all)")
    registration_keyframes: int = Field(3, ge=1, description="register against this many "
                                        "keyframes: those that see most of the scan at the "
                                        "predicted pose (overlap; the nearest among equals)")
    max_iterations: int = Field(20, ge=1, description="Gauss-Newton iterations per scan")
    converged_rotation_deg: float = Field(0.1, gt=0, description="converged when a step "
                                          "rotates less than this (small_gicp's default)")
    converged_translation_m: float = Field(1e-3, gt=0, description="... and moves less "
                                           "than this (small_gicp's default)")
    deskew: bool = Field(True, description="undo motion within a sweep (per-point times)")
    redeskew_rotation_deg: float = Field(0.5, ge=0, description="deskew again with the "
                                         "registered motion, and register again, when it "
                                         "turns this much more or less over the sweep than "
                                         "the predicted one (a hand-held sensor's nod, which "
                                         "constant velocity mispredicts)")
    redeskew_translation_m: float = Field(0.05, ge=0, description="... or moves this much "
                                          "more or less over the sweep (m)")
    use_imu: bool = Field(True, description="predict with IMU preintegration when the log "
                          "has an IMU")
    degeneracy_ratio: float = Field(0.006, gt=0, description="degenerate when the weakest "
                                    "translation direction holds less than this share of the "
                                    "Hessian's translation information (min eigenvalue / "
                                    "trace; 0.001-0.003 in a corridor or on a plane, >= 0.015 in "
                                    "rooms, halls and forests)")
    rotation_degeneracy_ratio: float = Field(1e-5, gt=0, description="the same for rotation")
    validate_surfaces: bool = Field(True, description="drop points whose surface faces away "
                                    "from the keyframe that saw it (GLIM's surface validation)")
    min_inliers: int = Field(50, ge=6, description="fewer correspondences: registration lost")
    buckets_per_map: int = Field(1 << 16, description="hash slots per keyframe map level "
                                 "(a power of two, at least twice max_points)")
    max_points: int = Field(32768, ge=16, description="most points per downsampled scan "
                            "(more are thinned evenly)")

    @model_validator(mode="after")
    def _map_fits(self) -> OdometryConfig:
        if self.buckets_per_map < 2 * self.max_points:
            raise ValueError(f"buckets_per_map ({self.buckets_per_map}) must be at least twice "
                             f"max_points ({self.max_points}) so a keyframe always fits")
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be smaller than max_range_m")
        return self
