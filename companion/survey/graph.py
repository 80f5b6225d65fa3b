"""The initial pose graph of a survey: which markers were seen together, and first poses for all.

Markers are linked when one frame shows both. ``marker_groups`` splits them
into groups never seen together; every group needs an anchor, else the map
cannot place it. ``initial_poses`` grows the map out from the anchors the way
the field does (ArUco's MarkerMapper, TagSLAM): a frame that sees known
markers gives camera pose candidates (each known marker's two IPPE poses,
and SQPnP over all known markers' points); an unknown marker seen in that
frame gets a candidate map pose per camera candidate and per IPPE pose of its
own; the candidate that most frames agree with wins, which resolves the IPPE
ambiguity that a single view of a small marker has. The marker with the most
frames shared with known markers is added first, and so on until every
marker of an anchored group is placed. The bundle adjustment then refines
all of it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.survey.observations import Sighting, SurveyFrame

AGREE_POSITION_M = 0.10      # two candidate marker poses this close ...
AGREE_ANGLE_DEG = 5.0        # ... and this close in angle tell the same story
AMBIGUITY_PX2 = 25.0 * 0.5 ** 2   # an IPPE branch this close (sum of squares, px^2) to the best is kept
ROBUST_CAP_PX = 4.0          # a marker's error counts at most this RMS when scoring a camera pose
AGREEING_RMS_PX = 20.0       # loose: the first marker poses are centimetres off
RIVAL_SHARE = 0.5            # a rival placement supported by this share of the chosen one's frames is tried too


def marker_groups(survey_frames, marker_ids: set[int]) -> list[set[int]]:
    """Groups of ``marker_ids`` linked by frames that see two or more of them (largest first)."""
    parent = {m: m for m in marker_ids}

    def root(m: int) -> int:
        while parent[m] != m:
            parent[m] = parent[parent[m]]
            m = parent[m]
        return m

    for frame in survey_frames:
        seen = [m for m in frame.marker_ids if m in parent]
        for m in seen[1:]:
            parent[root(m)] = root(seen[0])
    groups: dict[int, set[int]] = {}
    for m in marker_ids:
        groups.setdefault(root(m), set()).add(m)
    return sorted(groups.values(), key=lambda g: (-len(g), min(g)))


@dataclass(frozen=True)
class Rival:
    """A second placement of a marker that its linking frames support nearly as well as the chosen one.

    T_map_marker: (4, 4) the rival pose; support, rival_support: the distinct linking frames agreeing with the
    chosen pose and with the rival. A small marker seen from one standpoint only has two IPPE poses that fit
    its corners equally well: every frame of that standpoint supports both, and the images alone cannot say
    which is right (the flip turns it, and every marker placed through it, by degrees).
    """

    T_map_marker: np.ndarray
    support: int
    rival_support: int


def initial_poses(survey_frames, anchors: dict[int, np.ndarray], camera: CameraModel) -> dict[int, np.ndarray]:
    """T_map_marker (4, 4) of every marker linked to an anchor, by id (the anchors as given)."""
    return grow(survey_frames, anchors, camera)[0]


def grow(survey_frames, anchors: dict[int, np.ndarray], camera: CameraModel,
         placed: dict[int, np.ndarray] | None = None) -> tuple[dict[int, np.ndarray], dict[int, Rival]]:
    """(T_map_marker (4, 4) of every marker linked to an anchor by id, the anchors as given; the rivals of the
    markers whose placement was ambiguous, by id). ``placed``: markers whose first pose is already decided
    (a rival tried instead), placed when their turn comes."""
    known = dict(anchors)
    rivals: dict[int, Rival] = {}
    ippe = IppeCache(camera)
    shared = [f for f in survey_frames if len(f.sightings) >= 2]
    while True:
        candidates = _next_marker(shared, known)
        if candidates is None:
            return known, rivals
        marker_id, linking_frames = candidates
        if placed and marker_id in placed:
            known[marker_id] = placed[marker_id]
            continue
        known[marker_id], rival = _consensus_with_rival(marker_id, linking_frames, known, camera, ippe)
        if rival is not None and rival.rival_support >= RIVAL_SHARE * rival.support:
            rivals[marker_id] = rival


def _next_marker(survey_frames, known: dict[int, np.ndarray]):
    """(the unknown marker seen in the most frames together with a known one, those frames), or None."""
    links: dict[int, list[SurveyFrame]] = {}
    for frame in survey_frames:
        ids = frame.marker_ids
        if any(m in known for m in ids):
            for m in ids:
                if m not in known:
                    links.setdefault(m, []).append(frame)
    if not links:
        return None
    marker_id = max(links, key=lambda m: (len(links[m]), -m))
    return marker_id, links[marker_id]


def consensus_pose(marker_id: int, linking_frames, known, camera: CameraModel, ippe: "IppeCache") -> np.ndarray:
    """The map pose of a new marker that most linking frames agree with, averaged over those frames."""
    return _consensus_with_rival(marker_id, linking_frames, known, camera, ippe)[0]


def _consensus_with_rival(marker_id: int, linking_frames, known, camera: CameraModel,
                          ippe: "IppeCache") -> tuple[np.ndarray, Rival | None]:
    """(the consensus pose, the best-supported pose that disagrees with it, or None)."""
    poses, frame_of = [], []
    for k, frame in enumerate(linking_frames):
        sighting = next(s for s in frame.sightings if s.marker_id == marker_id)
        for T_camera_map in camera_pose_candidates(frame, known, camera, ippe):
            T_map_camera = frames.invert_transform(T_camera_map)
            for T_camera_marker in ippe.poses(frame, sighting):
                poses.append(T_map_camera @ T_camera_marker)
                frame_of.append(k)
    poses_arr, frame_of = np.array(poses), np.array(frame_of)
    agree = _agreement(poses_arr)
    # support: the number of distinct frames with a candidate that agrees
    support = [len(set(frame_of[agree[i]].tolist())) for i in range(len(poses_arr))]
    best = int(np.argmax(support))
    pose = _mean_pose(poses_arr, agree[best], frame_of)
    others = [i for i in range(len(poses_arr)) if not agree[best, i]]
    if not others:
        return pose, None
    second = max(others, key=lambda i: support[i])
    rival = Rival(_mean_pose(poses_arr, agree[second], frame_of), support[best], support[second])
    return pose, rival


def _mean_pose(poses: np.ndarray, members: np.ndarray, frame_of: np.ndarray) -> np.ndarray:
    """The mean of the candidate poses ``members`` (bool (N,)), one per frame: rotation mean, median position."""
    chosen = {}
    for i in np.flatnonzero(members):
        chosen.setdefault(int(frame_of[i]), i)  # one candidate per frame
    picked = poses[list(chosen.values())]
    R_mean = Rotation.from_matrix(picked[:, :3, :3]).mean().as_matrix()
    return frames.make_transform(R_mean, np.median(picked[:, :3, 3], axis=0))


def same_pose(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """Two marker poses (4, 4) that tell the same story (within AGREE_POSITION_M and AGREE_ANGLE_DEG)."""
    return bool(_agreement(np.array([T_a, T_b]))[0, 1])


def _agreement(poses: np.ndarray) -> np.ndarray:
    """(N, N) bool: candidate poses i and j within AGREE_POSITION_M and AGREE_ANGLE_DEG."""
    distance_m = np.linalg.norm(poses[:, None, :3, 3] - poses[None, :, :3, 3], axis=2)
    # the angle between R_i and R_j: trace(R_i^T R_j) = 1 + 2 cos(angle)
    traces = np.einsum("iab,jab->ij", poses[:, :3, :3], poses[:, :3, :3])
    cos_angle = np.clip((traces - 1.0) / 2.0, -1.0, 1.0)
    return (distance_m < AGREE_POSITION_M) & (cos_angle > math.cos(math.radians(AGREE_ANGLE_DEG)))


def camera_pose_candidates(frame: SurveyFrame, known: dict[int, np.ndarray], camera: CameraModel,
                           ippe: "IppeCache") -> list[np.ndarray]:
    """T_camera_map candidates from the known markers of a frame: the best and those nearly as good."""
    seen = [s for s in frame.sightings if s.marker_id in known]
    starts = [T_cm @ frames.invert_transform(known[s.marker_id]) for s in seen for T_cm in ippe.poses(frame, s)]
    if len(seen) >= 2:
        starts.append(_sqpnp(seen, known, camera))
    scored = sorted(((robust_cost_px2(T, seen, known, camera), k) for k, T in enumerate(starts)))
    best_cost = scored[0][0]
    return [starts[k] for cost, k in scored if cost <= best_cost + AMBIGUITY_PX2]


def frame_pose(frame: SurveyFrame, known: dict[int, np.ndarray], camera: CameraModel,
               ippe: "IppeCache | None" = None) -> tuple[np.ndarray, tuple[int, ...]] | None:
    """(T_camera_map, ids of the markers that agree with it) refined over those markers; None if fewer
    than two known markers agree."""
    ippe = ippe or IppeCache(camera)
    seen = [s for s in frame.sightings if s.marker_id in known]
    if len(seen) < 2:
        return None
    T_camera_map = camera_pose_candidates(frame, known, camera, ippe)[0]
    for _ in range(2):
        agreeing = [s for s in seen if _rms_px(T_camera_map, s, known, camera) < AGREEING_RMS_PX]
        if len(agreeing) < 2:
            return None
        T_camera_map = _refine(T_camera_map, agreeing, known, camera)
    return T_camera_map, tuple(s.marker_id for s in agreeing)


# ------------------------------------------------------------------ pieces

class IppeCache:
    """Each sighting's IPPE poses T_camera_marker (the second only if it fits nearly as well), computed once."""

    def __init__(self, camera: CameraModel):
        self.camera = camera
        self._poses: dict[tuple[int, int, int], list[np.ndarray]] = {}

    def poses(self, frame: SurveyFrame, sighting: Sighting) -> list[np.ndarray]:
        key = (frame.walk, frame.index, sighting.marker_id)
        if key not in self._poses:
            self._poses[key] = self._solve(sighting)
        return self._poses[key]

    def _solve(self, sighting: Sighting) -> list[np.ndarray]:
        corners_marker = np.ascontiguousarray(sighting.points_marker_m[:4])
        corners_px = np.ascontiguousarray(sighting.corners_px).reshape(4, 1, 2)
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(corners_marker, corners_px, self.camera.K, self.camera.dist,
                                                     flags=cv2.SOLVEPNP_IPPE_SQUARE)
        poses = [frames.transform_from_rotvec(rvecs[i], tvecs[i]) for i in range(count)]
        sse = [_sse_px2(self.camera, T, sighting.points_marker_m, sighting.points_px) for T in poses]
        return [T for T, e in zip(poses, sse) if e <= min(sse) + AMBIGUITY_PX2]


def _sse_px2(camera: CameraModel, T_camera_x: np.ndarray, points_x: np.ndarray, points_px: np.ndarray) -> float:
    """Sum of squared pixel errors of points given in frame x (inf if one is behind the camera)."""
    errors = camera.project_from(T_camera_x, points_x) - points_px
    sse = float(np.sum(errors ** 2))
    return sse if math.isfinite(sse) else math.inf


def _map_points(sighting: Sighting, known: dict[int, np.ndarray]) -> np.ndarray:
    return frames.transform_points(known[sighting.marker_id], sighting.points_marker_m)


def robust_cost_px2(T_camera_map: np.ndarray, seen: list[Sighting], known, camera: CameraModel) -> float:
    """Sum over markers of their squared errors, each capped at ROBUST_CAP_PX RMS (one bad marker cannot win)."""
    total = 0.0
    for s in seen:
        cap = len(s.points_px) * ROBUST_CAP_PX ** 2
        total += min(_sse_px2(camera, T_camera_map, _map_points(s, known), s.points_px), cap)
    return total


def _rms_px(T_camera_map: np.ndarray, sighting: Sighting, known, camera: CameraModel) -> float:
    return math.sqrt(_sse_px2(camera, T_camera_map, _map_points(sighting, known), sighting.points_px)
                     / len(sighting.points_px))


def _sqpnp(seen: list[Sighting], known, camera: CameraModel) -> np.ndarray:
    points_map = np.vstack([_map_points(s, known) for s in seen])
    points_px = np.vstack([s.points_px for s in seen])
    _, rvec, tvec = cv2.solvePnP(points_map, points_px, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    return frames.transform_from_rotvec(rvec, tvec)


def _refine(T_camera_map: np.ndarray, seen: list[Sighting], known, camera: CameraModel) -> np.ndarray:
    """Levenberg-Marquardt over the markers' points from T_camera_map."""
    points_map = np.vstack([_map_points(s, known) for s in seen])
    points_px = np.vstack([s.points_px for s in seen])
    rvec = frames.rotvec_from_rotation(T_camera_map[:3, :3]).reshape(3, 1)
    tvec = T_camera_map[:3, 3].reshape(3, 1).copy()
    rvec, tvec = cv2.solvePnPRefineLM(points_map, points_px, camera.K, camera.dist, rvec, tvec)
    return frames.transform_from_rotvec(rvec, tvec)
