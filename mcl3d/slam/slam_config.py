"""The parameters of Monte Carlo SLAM, one section per step of the filter (as in the
localizer's config). Lengths in metres, angles in degrees; each value converts to radians
where it is used. Saved as slam_config.yaml beside a run's outputs and loadable with the
`slam` command's config file."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from mcl3d.core.config import Section
from mcl3d.odometry.lidar_odometry import OdometryConfig


class FrontEndConfig(Section):
    """What SLAM keeps of a scan (the odometry front-end has its own settings)."""

    fov_deg: float = Field(360.0, gt=0, le=360, description="keep points within ±fov/2 of "
                           "the lidar's +x axis (the paper crops the backward half: 180)")
    scan_voxel_m: float = Field(0.25, gt=0, description="downsampling of scans and keyframe "
                                "clouds (m)")


class KeyframeConfig(Section):
    """When a scan becomes a keyframe, and the Gaussian voxel maps kept of it."""

    voxel_m: float = Field(0.5, gt=0, description="Gaussian voxel size of the keyframe maps "
                           "used for likelihood and correction (m)")
    overlap: float = Field(0.7, gt=0, le=1, description="new keyframe when the scan's voxel "
                           "overlap with the last keyframe drops below this (fraction)")
    overlap_voxel_m: float = Field(1.0, gt=0, description="voxel size of the overlap test (m)")
    max_points: int = Field(2048, ge=64, description="most points per keyframe map")
    capacity: int = Field(256, ge=2, description="most keyframes in a run (voxel maps are "
                          "allocated for this many)")


class PredictionNoiseConfig(Section):
    """The noise δ each particle draws around the odometry's motion (eq. 1)."""

    odometry_scale: float = Field(0.0625, ge=0, description="× the odometry's σ (its "
                                  "inverse Hessian overstates the per-scan error, and "
                                  "between loops a particle's noise is its error: "
                                  "docs/slam.md)")
    trans_per_m: float = Field(0.0025, ge=0, description="translation σ (m) per metre moved")
    rot_deg_per_m: float = Field(0.0125, ge=0, description="rotation σ (deg) per metre moved")
    rot_deg_per_deg: float = Field(0.0025, ge=0, description="rotation σ (deg) per degree "
                                   "turned")
    trans_min_m: float = Field(0.00025, ge=0, description="translation σ floor per scan (m)")
    rot_min_deg: float = Field(0.0025, ge=0, description="rotation σ floor per scan (deg)")
    max_odometry_sigma_m: float = Field(0.0025, gt=0, description="cap on the odometry's "
                                        "translation σ per scan (degenerate or lost "
                                        "registration) (m)")
    max_odometry_sigma_deg: float = Field(0.025, gt=0, description="the same for rotation "
                                          "(deg)")


class LoopClosureConfig(Section):
    """Which keyframes are a particle's neighbours, and which of them close a loop."""

    min_travel_m: float = Field(10.0, gt=0, description="a neighbour keyframe this far back "
                                "along the path is a loop (m)")
    neighbour_max_dz_m: float = Field(2.0, gt=0, description="keyframes more than this above "
                                      "or below a particle are not its neighbours (another "
                                      "floor) (m)")
    facing_gate: bool = Field(True, description="a loop keyframe must face within "
                              "front_end.fov_deg / 2 of the particle (not in the paper; see "
                              "docs/slam.md)")
    facing_neighbours: bool = Field(True, description="with the facing gate, an old "
                                    "keyframe facing away is not a neighbour either, so the "
                                    "nearest keyframes that can close a loop are chosen (a "
                                    "lane driven against its first pass finds the parallel "
                                    "lanes driven its way; docs/slam.md)")


class CorrectionConfig(Section):
    """Gauss-Newton steps on the GICP cost: toward the loop keyframes (eq. 5-10), and for
    particles without a loop toward their own newest keyframes."""

    points: int = Field(512, ge=16, description="scan points per likelihood and Gauss-Newton "
                        "evaluation")
    gn_iterations: int = Field(1, ge=0, description="Gauss-Newton steps per loop frame (0: no "
                               "gradient guidance)")
    min_inliers: int = Field(100, ge=6, description="correspondences needed for a step (of "
                             "`points`): a loop keyframe that sees little of the scan (the "
                             "next row of trees, seen from behind) pulls the wrong way")
    max_step_m: float = Field(1.0, gt=0, description="trust region of one step (m)")
    max_step_deg: float = Field(5.0, gt=0, description="trust region of one step (deg)")
    settled_step_m: float = Field(0.02, ge=0, description="a step this small means the "
                                  "particle is on the loop: later steps spread from here "
                                  "instead of from the oldest neighbour (m)")
    settled_step_deg: float = Field(0.2, ge=0, description="the same for rotation (deg)")
    refine_without_loop: bool = Field(False, description="particles without a loop take "
                                      "one step toward their own newest keyframes per scan, "
                                      "the prediction noise as prior (not in the paper; "
                                      "off: it chains scan-to-keyframe matches, "
                                      "docs/slam.md)")
    spread_after_step: bool = Field(True, description="a particle a step moved draws from "
                                    "the step's Gaussian posterior, so the cloud does not "
                                    "collapse on the likelihood's mode (not in the paper; "
                                    "see docs/slam.md)")


class LikelihoodConfig(Section):
    """The GICP log-likelihood that weighs the particles (eq. 2-3, 11)."""

    points_weight: float = Field(30.0, gt=0, description="independent points a scan is worth "
                                 "(tempering; see docs/slam.md)")
    outlier_cost: float = Field(0.0, ge=0, description="cost of a scan point with no voxel "
                                "(a matched point costs eᵀΩe; 0 as in the paper)")
    unmatched_as_typical: bool = Field(True, description="a scan point with no voxel also "
                                       "costs what a typical matched point costs against the "
                                       "recent map (the median over the cloud): no evidence "
                                       "either way; off (the paper), such a point is free, "
                                       "which rewards a loop keyframe for seeing less of the "
                                       "scan")
    truncated: bool = Field(False, description="a matched point costs at most outlier_cost: "
                            "missing a voxel and matching it badly cost the same (a truncated "
                            "Gaussian; not in the paper)")
    local_weight: float = Field(0.0, ge=0, le=1, description="a neighbour that is not a loop "
                                "costs this × its own cost + the rest × the cloud's median "
                                "such row (1: its own, as in the paper; 0: only loops "
                                "tell particles apart, as the odometry already matched "
                                "the scan to the recent map; docs/slam.md)")
    free_space_cost: float = Field(0.0, ge=0, description="cost of a scan point lying in "
                                   "space a neighbour keyframe saw through, or of a keyframe "
                                   "point in the scan's (docs/slam.md; 3 was studied); 0: "
                                   "off, as in the paper")
    free_space_margin_m: float = Field(0.3, ge=0, description="a point is in seen-through "
                                       "space when nearer than the keyframe's return by more "
                                       "than this (m) ...")
    free_space_margin_frac: float = Field(0.05, ge=0, description="... and by more than this "
                                          "fraction of the return's range")
    free_space_bin_deg: float = Field(2.0, gt=0, le=30, description="bin of each keyframe's "
                                      "spherical range image (deg)")
    free_space_points: int = Field(128, ge=1, description="scan points judged per keyframe "
                                   "(evenly of the scored ones; their count is scaled to all)")


class PruningConfig(Section):
    """Which particles die and are replaced by copies of living ones, and how hypotheses are
    counted."""

    posterior: float = Field(1e-8, ge=0, lt=1, description="dead below this posterior")
    likelihood_ratio: float = Field(1e-16, ge=0, lt=1, description="dead when the frame "
                                    "likelihood is below this times the best particle's")
    hypothesis_cell_m: float = Field(2.0, gt=0, description="grid cell for counting "
                                     "hypotheses (m)")


class ElevatorConfig(Section):
    """The elevator detector and the vertical random walk while it holds. `enclosure`
    (default) fires only when the scan is closed in every azimuth sector, as in a cab with
    its doors shut; `median` is the paper's test (median range under `median_range_m`),
    which also fires in narrow aisles and beside walls (docs/slam.md)."""

    detector: Literal["enclosure", "median", "off"] = Field(
        "enclosure", description="enclosure: every azimuth sector closed within "
        "enclosure_range_m; median: the paper's median range test; off")
    sectors: int = Field(12, ge=3, le=360, description="azimuth sectors across the field of "
                         "view (enclosure)")
    percentile: float = Field(90.0, gt=0, le=100, description="the range percentile of a "
                              "sector that must be under enclosure_range_m (enclosure)")
    enclosure_range_m: float = Field(3.0, gt=0, description="a sector is closed when its "
                                     "percentile range is below this (m): above a cab's "
                                     "half-diagonal, below a corridor's length (enclosure)")
    min_sector_points: int = Field(20, ge=1, description="a sector with fewer returns is "
                                   "open: nothing within the sensor's reach (enclosure)")
    median_range_m: float = Field(1.5, gt=0, description="elevator detected while the scan's "
                                  "median range is below this (median) (m)")
    sigma_z_m: float = Field(0.25, ge=0, description="vertical random walk per scan in the "
                             "elevator, without IMU (m)")
    imu_sigma_z_m: float = Field(0.01, ge=0, description="the same around the IMU's vertical "
                                 "motion (m)")
    resample_on_entry: bool = Field(True, description="resample every particle by weight "
                                    "when a ride starts, so the vertical walk spreads the "
                                    "likely particles' copies over the heights, not a few "
                                    "heavy particles to a few heights")
    exit_open_sectors: int = Field(3, ge=0, description="after a ride, scans are neither "
                                   "scored nor keyframes until this many sectors are open "
                                   "(the sensor has left the cab, whose open doors leave "
                                   "two: 3 was studied); 0: from the first scan the "
                                   "detector lets go")
    free_space_cost: float = Field(3.0, ge=0, description="the free-space term "
                                   "(likelihood.free_space_*) at this cost only while the "
                                   "floor guard holds the floors after a ride (0: off)")
    floor_guard: bool = Field(True, description="after a ride, prune each height stratum "
                              "on its own and keep every stratum's weight within "
                              "floor_max_gap_nats of the best, so every floor hypothesis "
                              "lives until the scans decide (mcl3d/slam/floor_guard.py)")
    floor_strata_m: float = Field(1.0, gt=0, description="height of a stratum (m): under "
                                  "the floor spacing")
    floor_max_gap_nats: float = Field(20.0, gt=0, description="a stratum's total weight is "
                                      "kept at least exp(-this) times the best stratum's")
    floor_decide_scans: int = Field(100, ge=1, description="the guard ends once every "
                                    "other floor has been held down at that bound for this "
                                    "many scored scans in a row")


class TrajectoryConfig(Section):
    """How the representative particle's keyframes become the written trajectory and map."""

    bridge_between_loops: bool = Field(True, description="between keyframes where the "
                                       "representative took a loop correction, its keyframes "
                                       "follow the odometry, bent least onto those anchors "
                                       "(the most likely path of its prediction noise given "
                                       "the ends; mcl3d/slam/loop_bridge.py); off: the "
                                       "particle's own poses, as in the paper")
    loop_graph: bool = Field(True, description="the keyframes solved as a pose graph instead: "
                             "odometry edges in the same drift covariance, and each loop the "
                             "representative took registered to convergence from the "
                             "filter's estimate (mcl3d/slam/loop_graph.py); takes precedence "
                             "over bridge_between_loops")
    structure_up: bool = Field(True, description="the loop graph also holds each keyframe's "
                               "tilt to the up its plumb surfaces show (trunks, walls: "
                               "mcl3d/slam/structure_up.py): without an IMU a half view's "
                               "pitch drift is not observed by the loops")


class SlamConfig(Section):
    """Everything `MonteCarloSlam` uses."""

    particles: int = Field(10000, ge=1, description="particles N")
    seed: int = Field(0, ge=0, lt=2**32, description="random seed (reproducible runs)")
    front_end: FrontEndConfig = FrontEndConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    prediction_noise: PredictionNoiseConfig = PredictionNoiseConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    correction: CorrectionConfig = CorrectionConfig()
    likelihood: LikelihoodConfig = LikelihoodConfig()
    pruning: PruningConfig = PruningConfig()
    elevator: ElevatorConfig = ElevatorConfig()
    odometry: OdometryConfig = OdometryConfig()
    trajectory: TrajectoryConfig = TrajectoryConfig()

    @model_validator(mode="after")
    def _keyframe_voxels_hold_scans(self) -> SlamConfig:
        if self.keyframes.voxel_m < self.front_end.scan_voxel_m:
            raise ValueError("keyframes.voxel_m must be >= front_end.scan_voxel_m")
        return self
