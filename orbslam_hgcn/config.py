"""Configuration: the frozen per-stage dataclasses a run reads (YAML sections ``map``,
``backend``, ``orb``, ``initializer``, ``tracking``, ``local_mapping``, ``system``,
``loop_closing``, ``relocalization``, ``threads``; gathered by
:class:`~orbslam_hgcn.runtime.system.Configs`), each with its defaults beside their meaning.

The files they come from (the camera YAML schema, the shipped configs, loading a file and
checking its sections, :func:`section_from_yaml`) are in :mod:`orbslam_hgcn.config_files`;
the configurations of the commands beside a run (FabmapConfig, VizConfig,
VocabularyConfig, TreeTrainConfig, HgcnTrainConfig) in :mod:`orbslam_hgcn.tool_config`.
Both are re-exported here: ``from orbslam_hgcn.config import X`` finds every name of the
three modules.
"""

from __future__ import annotations

import dataclasses
import math

# Re-exported: the callers import these from this module.
from orbslam_hgcn.config_files import (  # noqa: F401
    CONFIG_DIR,
    KIND_FAMILIES,
    NOT_SETTINGS,
    OTHER_SECTIONS,
    camera_from_dict,
    camera_to_dict,
    check_sections,
    dataset_settings,
    load_camera,
    load_yaml,
    resolve_config,
    save_camera,
    section_from_yaml,
    shipped_configs,
    stage_sections,
)
from orbslam_hgcn.errors import ConfigError
# Defined beside the two-view solver that reads it (geometry never imports this module).
from orbslam_hgcn.geometry.two_view import InitializerConfig  # noqa: F401
from orbslam_hgcn.tool_config import (  # noqa: F401
    FabmapConfig,
    HgcnTrainConfig,
    TreeTrainConfig,
    VizConfig,
    VocabularyConfig,
)


# --- Stage configurations -------------------------------------------------------------
# Each stage appends its frozen dataclass below, defaults beside their meaning.


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """The map model (defaults from ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO 2015)."""

    # Two keyframes are covisibility neighbours when they share at least this many map
    # points (ORB-SLAM: theta_min = 15); a keyframe with no such neighbour keeps its best one.
    covisibility_min_weight: int = 15
    # Covisibility edges of the essential graph need this many shared points (ORB-SLAM: 100).
    essential_min_weight: int = 100
    # Erasing an observation sets its point bad when fewer than this many remain
    # (ORB-SLAM MapPoint::EraseObservation discards points with nObs <= 2).
    min_observations_after_erase: int = 3


@dataclasses.dataclass(frozen=True)
class BackendConfig:
    """Pose-only refinement, bundle adjustment and the Sim(3) pose graph (ORB-SLAM defaults)."""

    # Chi-square 95% quantile for 2 DoF: a monocular observation with whitened squared
    # error above this is an outlier; the Huber threshold is its square root.
    chi2_mono: float = 5.991
    # Pose-only optimisation (ORB-SLAM PoseOptimization): rounds x iterations, each round
    # restarting from the initial pose with the current inlier set; the robust kernel is
    # dropped from this round on.
    pose_rounds: int = 4
    pose_iterations: int = 10
    pose_robust_rounds: int = 2
    # Fewer inliers than this and the pose counts as lost.
    pose_min_inliers: int = 10
    # Local BA: robust iterations, then outliers removed and this many more without kernel.
    local_ba_iterations: int = 5
    local_ba_refine_iterations: int = 10
    # Local BA solver: "schur" (compiled LM on the Schur complement,
    # orbslam_hgcn.backend.schur_ba) or "gtsam" (LM through a gtsam factor graph, the
    # reference). On real KITTI windows (28 free keyframes, 25,000 observations) one gtsam
    # iteration took about 100 ms, one compiled iteration about 10 ms, to the same result.
    local_ba_solver: str = "schur"
    # Whether a stop request (a waiting keyframe, a pause, the shutdown) may end local BA
    # during its robust iterations. ORB-SLAM2 polls its abort flag at every iteration. In
    # threaded runs here, the next keyframe then stopped nearly every local BA (198 of 202
    # in one run of the fr3 replay), and keyframe ATE on that replay was 0.48-1.38 cm over
    # 5 runs, against 0.27-0.44 cm over 3 runs with this False, at about 7% fewer frames/s.
    # False: the robust iterations always run, and a stop request takes effect before the
    # refining ones.
    local_ba_abort_robust: bool = False
    # Global BA iterations (ORB-SLAM: 10 after a loop, 20 at initialisation).
    global_ba_iterations: int = 10
    two_view_ba_iterations: int = 20
    # Essential-graph optimisation (ORB-SLAM OptimizeEssentialGraph: LM, 20 iterations).
    pose_graph_iterations: int = 20
    # Wall-clock cap in seconds on one BA call, checked between LM iterations (0: none).
    # gtsam holds the GIL during an iteration, so this bounds how long other threads wait.
    ba_time_budget_s: float = 0.0

    def __post_init__(self) -> None:
        if self.local_ba_solver not in ("schur", "gtsam"):
            raise ConfigError(f"backend.local_ba_solver: expected 'schur' or 'gtsam', found {self.local_ba_solver!r}")


@dataclasses.dataclass(frozen=True)
class ORBConfig:
    """ORB extraction (defaults of ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO 2015, and its
    ORBextractor: 1000 features, 8 levels, factor 1.2, FAST 20 with fallback 7 per cell)."""

    n_features: int = 1000  # keypoints per image, over all pyramid levels
    scale_factor: float = 1.2  # scale between consecutive pyramid levels
    n_levels: int = 8  # pyramid levels
    ini_th_fast: float = 20.0  # FAST threshold tried first in every cell
    min_th_fast: float = 7.0  # fallback FAST threshold for cells with no corner at ini_th_fast
    cell_size: int = 30  # side in pixels of the detection cells of each level
    edge_threshold: int = 19  # no keypoint closer than this to a level's border
    patch_size: int = 31  # rBRIEF patch side; orientation patch radius is patch_size // 2
    # Threads over the pyramid levels; the keypoints do not depend on it. 2 makes one
    # extraction about 15% faster on an idle 2-core machine, but the threaded system keeps
    # both cores busy, and there one thread per extraction gave as many or more frames/s.
    threads: int = 1


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Monocular tracking (ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V, and
    Tracking.cc / ORBmatcher.cc of ORB-SLAM2, whose values are the defaults here)."""

    # Initialisation: a reference frame needs more than this many keypoints, the pair this
    # many initialisation matches (window 100 px, ratio 0.9), and the map this many points
    # tracked by the second keyframe after the two-view BA.
    init_min_keypoints: int = 100
    init_min_matches: int = 100
    # Frames are extracted with this many times ORBConfig.n_features while initialising
    # (ORB-SLAM2's mpIniORBextractor: 2 x nFeatures).
    init_features_factor: float = 2.0
    init_window: float = 100.0
    init_ratio: float = 0.9
    init_min_points: int = 100
    # Constant-velocity model: window th * scale of the last keypoint's level (mono th = 15),
    # widened to 2 th when fewer than motion_min_matches matches are found; the pose is kept
    # with at least motion_min_inliers inliers observed by keyframes.
    motion_window: float = 15.0
    motion_min_matches: int = 20
    motion_min_inliers: int = 10
    # Reference-keyframe tracking: BoW matching with this ratio when a vocabulary is given;
    # without one, projection of the reference keyframe's points from the last pose in a
    # window of ref_window * scale pixels. Needs ref_min_matches matches.
    ref_bow_ratio: float = 0.7
    ref_window: float = 40.0
    ref_min_matches: int = 15
    # Local map: at most this many local keyframes; each keyframe sharing points with the
    # frame brings its best ref_covisibles covisible keyframes; a point is searched when
    # seen within acos(frustum_min_cos) of its mean viewing direction, in a window of
    # local_window * (2.5 or 4 by viewing angle) * scale px (local_window_relocalised just
    # after a relocalisation), best < local_ratio * second when both lie on one level.
    max_local_keyframes: int = 80
    local_covisibles: int = 10
    frustum_min_cos: float = 0.5
    local_window: float = 1.0
    local_window_relocalised: float = 5.0
    local_ratio: float = 0.8
    # Tracking succeeds with at least this many inliers after the local map (ORB-SLAM2
    # TrackLocalMap: 30, or 50 within max_frames of a relocalisation).
    min_inliers: int = 30
    min_inliers_relocalised: int = 50
    # Keyframe decision (ORB-SLAM2 NeedNewKeyFrame, monocular): c1a max_frames passed
    # (0: the camera fps), c1b min_frames passed and local mapping idle, c2 fewer than
    # ref_ratio of the reference keyframe's points tracked and more than keyframe_min_inliers.
    min_frames: int = 0
    max_frames: int = 0
    ref_ratio: float = 0.9
    # ... and c1b also waits this many seconds of camera time after the last keyframe (not
    # in ORB-SLAM, whose keyframe rate is set by how long local mapping takes on the
    # machine; see keyframe_decision). 0: none. The KITTI camera settings
    # (configs/kitti_*.yaml) use 0.15 s: every other frame of 10 Hz driving, ORB-SLAM3's
    # density there; at 0.3 s hand-held 30 Hz sequences keep their keyframe rate.
    min_keyframe_interval_s: float = 0.3
    # ... once the map holds this many keyframes (a young map, refined by every keyframe,
    # gets them as fast as ORB-SLAM would: local mapping of a few keyframes is quick).
    min_keyframe_interval_from: int = 5
    # c1c: a frame tracking fewer points than this makes a keyframe whatever the interval
    # (the local map is running out), and in threaded runs the tracker waits for a busy
    # local mapping to take it (threads.keyframe_wait_s). Twice min_inliers.
    keyframe_urgent_inliers: int = 60
    keyframe_min_inliers: int = 15
    # A map with at most this many keyframes is discarded when tracking is lost, and
    # initialisation starts over (ORB-SLAM2: 5).
    reset_max_keyframes: int = 5
    # With an atlas (the system's default): once tracking has been lost this many seconds
    # of camera time and relocalisation keeps failing, a new map is started and the lost
    # one kept, to be merged when the camera comes back to it (ORB-SLAM3 waits a few seconds
    # before it gives a map up; 1 s here, so that a run goes on within about a second of a
    # stretch it cannot track).
    new_map_after_s: float = 1.0
    # Matches the pose optimiser rejects are kept for the new keyframe (ORB-SLAM2 lets
    # them pass so that local BA decides on them); False drops them.
    keyframe_keeps_outliers: bool = True
    # CameraTrajectory.txt: each tracked frame keeps its inlier matches (about 17 bytes
    # each: some 4 KB a frame at 1000 features), and when the run ends its pose is
    # optimised again, motion-only, against the final map: the points it was tracked with,
    # followed through fusions, at their final positions (a frame with fewer than
    # min_inliers of them left, and a keyframe's own frame, keep the pose carried by their
    # reference keyframe). A frame's tracked pose carries the error of the points it saw
    # then, often just triangulated, which local BA later reduces for the keyframes only.
    # First 500 frames of the fr3 replay: camera ATE 0.192 cm against 0.228 cm carried
    # (keyframes 0.191 cm); the whole replay 0.382 against 0.400 cm (keyframes 0.393);
    # KITTI 00 42.71 against 42.85 cm (keyframes 43.86); 0.13 ms a frame at the end.
    # False: each frame's pose relative to its reference keyframe, as ORB-SLAM2 writes it.
    refine_frame_poses: bool = True


@dataclasses.dataclass(frozen=True)
class LocalMappingConfig:
    """Local mapping (ORB-SLAM, T-RO 2015, Sec. VI; LocalMapping.cc of ORB-SLAM2)."""

    # Recent points are culled when found in fewer than cull_found_ratio of the frames
    # predicted to see them, or when cull_after_keyframes keyframes after their creation
    # they are seen by at most cull_max_obs keyframes (monocular: 2); they leave the
    # recent list after cull_settled_keyframes keyframes.
    cull_found_ratio: float = 0.25
    cull_after_keyframes: int = 2
    cull_max_obs: int = 2
    cull_settled_keyframes: int = 3
    # Triangulation against the best triangulation_neighbours covisible keyframes (mono 20),
    # skipped when baseline / median scene depth of the neighbour is below min_baseline_ratio.
    triangulation_neighbours: int = 20
    min_baseline_ratio: float = 0.01
    # ORB-SLAM2 matches for triangulation without the rotation-consistency check.
    triangulation_check_orientation: bool = False
    # Fusion (SearchInNeighbors): best fuse_neighbours covisible keyframes and the best
    # fuse_second_neighbours of each; projection window fuse_window * scale px.
    fuse_neighbours: int = 20
    fuse_second_neighbours: int = 5
    fuse_window: float = 3.0
    # Local BA (iterations in BackendConfig: 5 robust, outliers out, 10 more) and a cap on
    # its CPU time in seconds, checked between iterations (0: none; like any stop request,
    # only from the refining iterations on unless backend.local_ba_abort_robust). The
    # iterations bound a typical window to well under the cap; the cap guards against
    # unusually large windows.
    # CPU time, not wall time, so that results do not depend on the machine's load.
    local_ba: bool = True
    ba_cpu_budget_s: float = 1.5
    # At most this many free keyframes in local BA: the new one and its best covisible
    # ones; the other covisible keyframes are held fixed (0: all free, as ORB-SLAM).
    ba_max_keyframes: int = 0
    # Local BA beside triangulation and fusion: its window is cut once the keyframe is
    # inserted (the keyframe, its covisible keyframes and the points they already see), solved
    # in a thread of its own while the mapping thread triangulates and fuses (the compiled
    # solver releases the GIL), and written back after fusion, where ORB-SLAM's order would
    # start it; the keyframe's new points join the next keyframe's BA. False: ORB-SLAM's
    # order (BA after fusion, over the new points too). The result does not depend on
    # timing: the window is a copy and the write-back comes at the same step every time.
    # Unpaced, idle 2-core Xeon (printed when it became the default, 3 runs each alternated
    # on KITTI): KITTI 00 frames 0-159 (KITTI's settings) 3.44-3.59x the camera's rate
    # against 2.87-2.94x, keyframe / camera ATE 37.16 / 36.71 cm against 38.79 / 39.94; the
    # fr3_replay_hard render (2613 frames) 0.22 / 0.23 cm against 0.29 / 0.30; TUM fr3
    # sitting_xyz 0.80 / 0.80 cm against 0.99 / 0.81 (142 frames tracked against 143); two
    # 600-frame street renders 106.6 / 106.0 and 84.1 / 84.7 cm against 93.8 / 93.1 and
    # 89.5 / 91.9.
    ba_beside_mapping: bool = True
    # Keyframe culling: a keyframe is redundant when more than cull_kf_redundant of its
    # points are seen by at least cull_kf_min_obs other keyframes at the same or a finer
    # scale (octave at most one level above).
    keyframe_culling: bool = True
    cull_kf_redundant: float = 0.9
    cull_kf_min_obs: int = 3
    # Track words (flat vocabularies: kmeans, hgcn): a keyframe's BoW vector, made after
    # triangulation and fusion, takes for each feature with a track the word of the mean of
    # the track's reduced descriptors in keyframes up to this one
    # (orbslam_hgcn.vocabulary.track_words); FeatureVectors and frames keep lone words.
    track_words: bool = False
    # How track words are made: "mean" (above) or "network": the graph network over the
    # feature's most recent causal track mates (orbslam_hgcn.vocabulary.track_network),
    # which needs a vocabulary holding one (--vocab hgcn_graph).
    track_words_by: str = "mean"

    def __post_init__(self) -> None:
        if self.track_words_by not in ("mean", "network"):
            raise ConfigError(
                f"local_mapping.track_words_by: expected 'mean' or 'network', found {self.track_words_by!r}")


@dataclasses.dataclass(frozen=True)
class SystemConfig:
    """The sequential system: what runs, and how the run is reported."""

    local_mapping: bool = True  # run the local mapper on every new keyframe
    progress: bool = True  # show a progress bar with fps and the tracking state


@dataclasses.dataclass(frozen=True)
class LoopClosingConfig:
    """Loop detection and Sim(3) loop correction (ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO
    2015, Sec. VII; LoopClosing.cc / ORBmatcher.cc / Optimizer.cc of ORB-SLAM2, whose values
    are the defaults here)."""

    # False: keyframes are only indexed in the keyframe database (for relocalisation).
    enabled: bool = True
    # No detection until this many keyframes exist after the map's start or the last loop.
    min_keyframes_between: int = 10
    # A candidate group must be consistent with the groups of this many previous keyframes.
    consistency_threshold: int = 3
    # SearchByBoW between the keyframe and a candidate: ratio, and matches needed.
    bow_ratio: float = 0.75
    min_bow_matches: int = 20
    # Candidates share more than 0.8 x the most shared words: as a raw count, as ORB-SLAM
    # does (False), or counted per word of each keyframe (True; see
    # KeyframeDatabase._detect). Relocalisation uses True; for loops the raw count is kept:
    # on the fr3 replay with the shipped HGCN vocabulary, True found no loop at the revisit
    # (every candidate failed the BoW-match stage) where False closes it.
    common_words_per_word: bool = False
    # Sim3Solver RANSAC (0.99, 20 inliers, 300 iterations); fix_scale only for stereo/RGB-D.
    sim3_probability: float = 0.99
    sim3_min_inliers: int = 20
    sim3_max_iterations: int = 300
    fix_scale: bool = False
    seed: int = 0  # RANSAC sample seed (reproducible runs)
    # Guided matching with the RANSAC similarity (SearchBySim3): window x level scale.
    sim3_search_window: float = 7.5
    # Sim(3) refinement (OptimizeSim3): Huber / outlier chi2 gate, iterations before and
    # after removing outliers (the second run is 10 when some were removed), inliers needed.
    sim3_opt_chi2: float = 10.0
    sim3_opt_iterations: int = 5
    sim3_opt_more_iterations: int = 10
    sim3_opt_min_inliers: int = 20
    # Sigma (log scale) of a prior holding the refined scale near the closed-form one; not in
    # ORB-SLAM: with a short baseline the reprojection errors leave the scale free (0: off).
    sim3_scale_prior_sigma: float = 0.05
    # Loop-side points projected into the keyframe with the similarity: window x level
    # scale, and matches needed in total to accept the loop.
    projection_window: float = 10.0
    min_total_matches: int = 40
    # Loop fusion window (SearchAndFuse) x level scale.
    fuse_window: float = 4.0
    # Points are searched when seen within acos(this) of their mean viewing direction.
    min_view_cos: float = 0.5
    # Global BA after the essential-graph optimisation (ORB-SLAM2 runs it in a thread),
    # its iterations and wall-time bound in seconds (0: none).
    global_ba: bool = True
    global_ba_iterations: int = 10
    global_ba_time_budget_s: float = 0.0

    def __post_init__(self) -> None:
        if self.consistency_threshold < 0 or self.min_keyframes_between < 0:
            raise ConfigError("loop_closing: consistency_threshold and min_keyframes_between must be >= 0")
        if not 0.0 < self.bow_ratio <= 1.0 or not 0.0 < self.sim3_probability < 1.0:
            raise ConfigError("loop_closing: bow_ratio must be in (0, 1] and sim3_probability in (0, 1)")


@dataclasses.dataclass(frozen=True)
class RelocalizationConfig:
    """Relocalisation of a lost frame (ORB-SLAM, T-RO 2015, Sec. V-C; Tracking::Relocalization
    of ORB-SLAM2: BoW candidates, EPnP in RANSAC, pose refinement, guided search)."""

    bow_ratio: float = 0.75  # SearchByBoW ratio between a candidate keyframe and the frame
    min_bow_matches: int = 15  # candidates with fewer matches are skipped
    # Beyond ORB-SLAM: a candidate with fewer BoW matches is matched again over all its
    # points' descriptors before it is skipped (blurred, over-exposed frames).
    exhaustive_fallback: bool = True
    # Beyond ORB-SLAM: when every database candidate fails, try up to this many keyframes
    # more, the candidates' best covisible ones (0: none).
    covisible_fallback: int = 5
    # Database candidates share more than 0.8 x the most shared words, counted per word of
    # each keyframe (True) or as ORB-SLAM's raw count (False; see KeyframeDatabase._detect).
    common_words_per_word: bool = True
    # PnPsolver::SetRansacParameters(0.99, 10, 300, 4, 0.5, 5.991).
    pnp_probability: float = 0.99
    pnp_min_inliers: int = 10
    pnp_max_iterations: int = 300
    pnp_min_set: int = 4
    pnp_epsilon: float = 0.5
    pnp_chi2: float = 5.991
    seed: int = 0  # RANSAC sample seed
    # Pose-only refinement must keep this many inliers to go on with a candidate.
    min_pose_inliers: int = 10
    # Guided search of the candidate's points when the pose has fewer than min_inliers:
    # window x level scale and largest Hamming distance, first wide, then narrow (applied
    # when the refined pose has more than narrow_min_inliers inliers).
    wide_window: float = 10.0
    wide_max_dist: int = 100
    narrow_window: float = 3.0
    narrow_max_dist: int = 64
    narrow_min_inliers: int = 30
    min_inliers: int = 50  # inliers to accept the relocalisation


@dataclasses.dataclass(frozen=True)
class ThreadsConfig:
    """How the system runs its stages (YAML section ``threads``): in order on the calling
    thread, or local mapping and loop closing in worker threads as ORB-SLAM does."""

    # True: tracking, local mapping and loop closing in order, one frame at a time; results
    # are identical on every run. False (the default of run, the API and ORB-SLAM): local
    # mapping and loop closing in worker threads. ``run --sequential`` and
    # ``Slam(sequential=True)`` set it.
    sequential: bool = False
    # Threaded only: solve the BAs that run in gtsam (global BA, the essential graph, local
    # BA with backend.local_ba_solver "gtsam") in child processes. gtsam keeps the GIL while
    # it iterates, so a BA solved in a thread of this process stalls tracking.
    process_solver: bool = True
    # Threaded only: solve local BA with the compiled Schur solver (backend.local_ba_solver
    # "schur", the default) in a child process too (True), or in the mapping thread (False).
    # The compiled solver releases the GIL while it iterates, so in the thread it stalls
    # nothing, and no problem is pickled to a process and back; the run also starts one
    # process fewer. On KITTI 00 frames 0-159 (unpaced, idle 2-core Xeon, 3 rounds
    # alternated) the span from the first frame to the last pose was 3.72-3.81 s in the
    # thread against 4.20-4.29 s in a process, with the same poses.
    local_ba_process: bool = False
    # Niceness added to the BA processes of paced runs: on a machine with few cores,
    # extraction and tracking get the CPU first, and BA the time they leave (local BA's CPU
    # budget is counted in CPU time, so it does not shrink). Unpaced runs (speed 0) leave
    # the BA processes at the tracker's priority: with mapping_sync "points" the tracker
    # waits for each local BA after the next frame, so a local BA process
    # (local_ba_process) starved by the work ahead (extraction) holds the tracker. On KITTI
    # 00 (idle 2-core Xeon, 3 rounds alternated, local BA in its process) unpaced runs took
    # 4.19-4.59 s from the first frame to the last pose with 0 against 4.50-4.77 s with 10,
    # the same poses.
    solver_nice: int = 10
    # Niceness added to the local mapping and loop closing threads (Linux): the extraction
    # process and the tracking thread get the CPU before them.
    worker_nice: int = 5
    # Unpaced runs (speed 0) only: niceness added to the image reader thread and the
    # extraction process (Linux). They then work ahead of the tracker (prefetch_frames) and
    # are off its path, so the tracking thread gets the CPU first. On the 640x480 fr3 replay
    # (500 frames, idle 2-core machine, 8 pairs alternated with 0) the span from the first
    # frame to the end fell in 7 pairs (6% at the median, up to 18%; +1% in the other), and
    # tracking's wall time per frame in all 8; on KITTI 00, -9% to +3% over 3 pairs (within
    # the noise). The cost: beside a normal-priority CPU job, which now takes the CPU from
    # the extraction process, the span grew in 4 of 5 pairs (0-12%, 5% at the median, KITTI
    # and fr3); 0 turns it off. Paced runs leave both at the tracker's priority: a frame's
    # latency counts its extraction.
    ahead_nice: int = 3
    # Threaded only: System.run reads images ahead on a thread of its own and extracts the
    # next frame's ORB features while the current frame is tracked.
    prefetch: bool = True
    # Threaded with prefetch: extract in a child process. Extraction's Python parts (corner
    # scores, quadtree, keypoint objects) hold the GIL; on a thread they contend with
    # tracking and local mapping for it.
    extraction_process: bool = True
    # Threaded, unpaced (speed 0) with prefetch: extraction may run this many frames ahead
    # of the tracker while it tracks (one while it initialises or relocalises, when the next
    # frame's extractor may change), so the extraction process keeps working while the
    # tracker waits for local mapping. Unpaced KITTI 00, 3 runs each alternated on an idle
    # machine: 7.4-8.5 s (median 8.3) from the first frame to the end with 3, 8.6-9.6 s
    # (8.8) with 1, the same poses; a frame's latency then counts its wait in the queue.
    # Deeper still (10 against 3, alternated on an idle machine, the same poses every
    # time): on the 640x480 fr3 replay (500 frames; decoding its PNGs costs about as much
    # CPU as extracting them, and the reader and extraction run ahead together) the span
    # fell in 9 of 9 pairs, by 1.0-5.5% (3.4% at the median); on KITTI 00 by 3.4% in
    # 2 of 2; 20 and 40 were no faster than 10 on the replay (2 runs each).
    # Paced runs stay one frame ahead: with 3, KITTI 00 beside a normal-priority job had
    # latency p95 96-139 ms against 74-81, the frames extracted early taking the core that
    # the local mapping the tracker waits for needs.
    prefetch_frames: int = 10
    # Threaded only: System.run hands frame i to the tracker no earlier than
    # (t_i - t_0) / speed seconds after frame 0, t being the dataset's timestamps, as a
    # camera delivers them (ORB-SLAM's example programs pace datasets the same way). Local
    # mapping makes a keyframe whenever it is free, so a run that outruns the camera gets
    # fewer keyframes, and more so on a faster machine. 0: as fast as frames are processed.
    speed: float = 1.0
    # Threaded only: when a keyframe has been due for a camera-second (ORB-SLAM's c1a and
    # c2) and only a busy local mapping keeps the tracker from making it, wait up to this
    # many seconds after the frame for mapping to accept one (0: never; ORB-SLAM does not
    # wait). At the camera's rate mapping rarely falls that far behind; a run faster than
    # the camera would otherwise outrun it until tracking is lost.
    keyframe_wait_s: float = 0.5
    # Paced threaded runs (speed > 0) with prefetch: False (the default, for recorded files:
    # image folders, datasets, videos) processes every frame; a run that the machine cannot
    # keep at the camera's rate falls behind the clock instead, as ORB-SLAM3's example
    # programs do, and stats.json says by how much (real_time). True (a live source,
    # ``orbslam-hgcn run --drop-late``) drops frames as a camera driver whose queue holds
    # frame_buffer_s seconds of frames does: see frame_buffer_s.
    drop_late: bool = False
    # With drop_late: a frame is dropped unprocessed when the camera would already have
    # delivered the frames of the next frame_buffer_s seconds by the time the system is
    # ready for it (counted as "dropped" in stats.json): the system never falls further
    # behind than that, and catches up after a stall without skipping the frames in
    # between. 0: no frame is dropped. With a queue of one frame (ORB-SLAM's ROS node
    # subscribes with a queue of 1), the fr3 replay with blur (30 Hz) dropped 2.6% of its
    # frames on an idle 2-core machine, on stalls of a frame or two, and a KITTI run (10 Hz)
    # whose tracker waited 0.8 s for local mapping lost its map on the 5-frame gap it then
    # had to bridge.
    frame_buffer_s: float = 0.5
    # Threaded runs: after handing a keyframe to local mapping, the tracker waits (at
    # most this many seconds) until mapping has finished it, so that the next frames are
    # tracked against its points and pose as a sequential run would track them; the frames
    # that arrive meanwhile wait and the run falls behind the clock (it catches up at the
    # next frames, which are due already). When every keyframe is mapped within the bound,
    # the run gives exactly the sequential run's result. With drop_late the wait also ends
    # half the frame queue after the next frame's arrival, so that no frame is dropped for
    # it. Unpaced runs (speed 0) wait too: ahead of mapping, a KITTI run under load lost its
    # track on frame 24. 0: never waits (as ORB-SLAM's threads). Frames tracked ahead of a busy mapping
    # are tracked against a stale local map, and their poses drift from the keyframes':
    # with 1.5 s of mapping stalled on a synthetic replay, 20-30 mm against 1 mm for the
    # keyframes. The default bound (5 s, was 0.5 s) only guards against a stalled stage: on
    # a loaded 2-core machine KITTI keyframes took up to 3 s to map.
    sync_mapping_s: float = 5.0
    # When the tracker waits for local mapping (threads.sync_mapping_s > 0): "each" after
    # every keyframe, until mapping has finished it (the sequential run's result; the wait
    # lands in the next frame's latency: p95 80-152 ms on KITTI 00, idle to loaded); "due"
    # only when the next keyframe is due by the rules (keyframe_decision, c1b's interval
    # included) and mapping has not finished the previous one, local BA included; the frame
    # then searches the local map again and becomes the keyframe. At most one keyframe is
    # in flight, none is skipped for a busy mapping, and the frames between two keyframes
    # are tracked without waiting, against a local map that may lack the newest keyframe's
    # points. "due" is not the default: on KITTI 00 beside other jobs (load average 10-16)
    # its keyframe ATE was 37.7-53.8 cm over 9 runs (median about 46) against 38.65 cm in
    # every "each" run, for a latency p95 that the other jobs' load left about as high.
    # "points" (the default): after a keyframe, until mapping has triangulated its new points
    # and fused them with the neighbours' (insert, words, triangulation, fusion); mapping
    # then solves its local BA (beside the tracker, the GIL released) but holds before
    # writing it back, and before culling, until the next frame is tracked; after that frame
    # the tracker waits for mapping to finish. So the next frame tracks against the
    # keyframe's points, mapping works while frames arrive, and every frame sees the same map
    # whatever the load: on KITTI 00, 9 runs idle and beside nice-19 and normal-priority jobs
    # (load average 5-13 from other work) and 3 unpaced runs all gave 51 keyframes, keyframe
    # ATE 30.87 cm and camera ATE 32.46 cm ("each": 52, 39.80 and 37.12 cm). Idle,
    # alternating with "each", latency p95 33-68 ms against 50-70 ms; unpaced 17.2 frames/s
    # against 15.2. Earlier forms: holding before local BA's solve, 42.59 cm; waiting only
    # for triangulation, not fusion, 49.45 cm with 50 keyframes (both deterministic over 9
    # runs). Those runs were on an AMD EPYC machine; on an Intel Xeon one the same code
    # gives 49 keyframes, 43.86 cm and 42.85 cm in every run, paced or unpaced, idle or
    # beside other jobs (sequential: 53 keyframes, 45.51 cm): still one map whatever the
    # load, but not the same map on every CPU. (Camera ATE 42.70 cm since the frames are
    # optimised again at the end, tracking.refine_frame_poses.)
    mapping_sync: str = "points"
    # Threads that OpenCV's and faiss's (OpenMP) pools may start in the process that tracks
    # and maps (System.run sets them, stats.json records them; the extraction process uses
    # one OpenCV thread). 0: the libraries' own defaults (one per core). One thread was
    # expected to help on 2 cores shared by tracking, mapping, extraction and BA, but unpaced
    # KITTI runs on a shared machine (load average 11-17, alternated) gave 3.4 and 2.0
    # frames/s with 1 against 3.1 and 4.1 with the defaults (HGCN insert step median 287 and
    # 458 ms against 214 and 211 ms), so the defaults stay until a quieter measurement.
    library_threads: int = 0

    def __post_init__(self) -> None:
        for name in ("solver_nice", "worker_nice", "ahead_nice"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 19):
                raise ConfigError(f"threads.{name}: must be an integer in [0, 19] (niceness added), found {value!r}")
        if not (math.isfinite(self.speed) and self.speed >= 0):
            raise ConfigError(f"threads.speed: must be a finite number >= 0 (0: no pacing), found {self.speed!r}")
        if not (math.isfinite(self.keyframe_wait_s) and self.keyframe_wait_s >= 0):
            raise ConfigError(f"threads.keyframe_wait_s: must be a finite number >= 0, found {self.keyframe_wait_s!r}")
        if not (isinstance(self.library_threads, int) and self.library_threads >= 0):
            raise ConfigError(f"threads.library_threads: must be an integer >= 0 (0: the libraries' defaults), "
                              f"found {self.library_threads!r}")
        if not (math.isfinite(self.sync_mapping_s) and self.sync_mapping_s >= 0):
            raise ConfigError(f"threads.sync_mapping_s: must be a finite number >= 0 (0: off), found {self.sync_mapping_s!r}")
        if not (isinstance(self.prefetch_frames, int) and not isinstance(self.prefetch_frames, bool)
                and self.prefetch_frames >= 1):
            raise ConfigError(f"threads.prefetch_frames: must be an integer >= 1, found {self.prefetch_frames!r}")
        if self.mapping_sync not in ("each", "due", "points"):
            raise ConfigError(f"threads.mapping_sync: must be each, due or points, found {self.mapping_sync!r}")
        if not (math.isfinite(self.frame_buffer_s) and self.frame_buffer_s >= 0):
            raise ConfigError(
                f"threads.frame_buffer_s: must be a finite number >= 0 (0: never drop a frame), found {self.frame_buffer_s!r}"
            )
