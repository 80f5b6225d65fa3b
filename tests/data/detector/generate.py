"""Render the detector's golden test frames (run once; the PNGs and JSONs are committed).

    PYTHONPATH=. python tests/data/detector/generate.py

Each NAME.png (400 x 300, 8-bit gray; markers with a 45-55 px inner square) comes with NAME.json:

    {"parity": 2, "markers": [{"symbol": "A", "id": 0, "corners": [[x, y] x 4],
      "path": "square" | "circles", "occlusion": "none" | "strip_1_8" | ...}], "note": "...",
     "params": "for_footage"}

"params" (optional): the markers are those ``DetectorParams.for_footage`` finds (the survey's detector),
not the daemon's default.

corners are the renderer's ground truth (inner square TL, TR, BR, BL of the
upright marker, through the same camera model), not detector output; path is
the path that must find the marker. Frames with "markers": [] must yield
nothing. Everything is drawn by ``companion.sim`` with fixed poses and seeds.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from companion.geometry import frames
from companion.sim import occluders
from companion.sim import raster
from companion.sim import scenes
from companion.geometry.camera import intrinsics_from_hfov
from companion.markers.layout import MarkerLayout

HERE = Path(__file__).resolve().parent
W, H = 400, 300
SIZE_M = 0.15


def pose(distance_m: float, spin_deg: float, tilt_deg: float = 0.0, offset_px=(0.0, 0.0),
         tilt_axis_deg: float = 0.0) -> np.ndarray:
    """T_camera_marker: an upright marker ahead, spun about its normal, tilted about an in-plane axis."""
    K = intrinsics_from_hfov(W, H, 70.0)
    axis = math.radians(tilt_axis_deg)
    tilt = math.radians(tilt_deg)
    R_tilt = frames.rotation_from_rotvec([math.cos(axis) * tilt, math.sin(axis) * tilt, 0.0])
    R = R_tilt @ frames.rot_z(math.radians(spin_deg)) @ frames.R_camera_marker_face_on()
    centre = distance_m * np.linalg.solve(K, [K[0, 2] + offset_px[0], K[1, 2] + offset_px[1], 1.0])
    return frames.make_transform(R, centre)


def scene(name: str, markers, parity: int = 2, note: str = "", seed: int = 0, degradations=None,
          background_kind: str = "clutter"):
    """markers: list of (texture, T, expected path or None for 'must not be found', occlusion, occluder or None)."""
    rng = np.random.default_rng(seed)
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), np.zeros(5), W, H)
    background = scenes.clutter_image(rng, (W, H)) if background_kind == "clutter" else float(background_kind)
    quads, placed = [], []
    for texture, T, path, occlusion, occluder in markers:
        quads.append(raster.marker_quad(texture, SIZE_M, T, gain=rng.uniform(0.75, 0.92), offset=rng.uniform(8, 25)))
        placed.append((texture, T, len(quads) - 1, path, occlusion))
        if occluder is not None:
            quads.append(occluder)
    rendering = renderer.render(quads, np.eye(4), background)
    degradations = degradations or scenes.BASE_DEGRADATIONS
    image = degradations.apply(rendering.image, rng)
    expected = []
    layout = MarkerLayout(parity)
    for texture, T, index, path, occlusion in placed:
        if path is None:
            continue
        truth = raster.marker_truth(renderer, rendering, texture, SIZE_M, T, np.eye(4), index)
        expected.append({"symbol": layout.dictionary.symbol_of(texture.marker_id), "id": texture.marker_id,
                         "corners": np.round(truth.corners_px, 3).tolist(), "path": path, "occlusion": occlusion})
    cv2.imwrite(str(HERE / f"{name}.png"), image)
    (HERE / f"{name}.json").write_text(json.dumps({"parity": parity, "markers": expected, "note": note}, indent=1) + "\n")


def main() -> None:
    rs = {p: MarkerLayout(p) for p in (2, 4)}

    def tex(marker_id, parity=2):
        return raster.rs_marker_texture(rs[parity], marker_id)

    rng = np.random.default_rng(1)

    # square path, all four upright rotations (and tilts)
    scene("square_rotations", [
        (tex(0), pose(0.9, 0, 20, (-100, -72), 30), "square", "none", None),
        (tex(13), pose(0.9, 90, 25, (100, -72), 120), "square", "none", None),
        (tex(26), pose(0.9, 180, 15, (-100, 72), 200), "square", "none", None),
        (tex(39), pose(0.9, 270, 30, (100, 72), 300), "square", "none", None),
    ], note="square path at 0, 90, 180 and 270 degrees")

    # circles path, all four rotations: a corner patch hides one inner corner of each
    markers = []
    for k, (marker_id, offset) in enumerate(zip((5, 18, 31, 44), ((-100, -72), (100, -72), (-100, 72), (100, 72)))):
        T = pose(0.9, 90 * k + 8, 18, offset, 60 * k)
        markers.append((tex(marker_id), T, "circles", "corner",
                        occluders.corner_occluder(tex(marker_id), SIZE_M, T, 0.25, (k + 1) % 4, rng, level=70 + 40 * k)))
    scene("circles_rotations", markers, note="corner patches; circles path at 0, 90, 180 and 270 degrees", seed=2)

    # side strips (border included), dark and light
    T1, T2 = pose(0.85, 20, 15, (-95, 0), 90), pose(0.85, -35, 25, (95, 10), 10)
    scene("strip_1_8", [
        (tex(7), T1, "circles", "strip_1_8", occluders.strip_occluder(tex(7), SIZE_M, T1, 1 / 8, "left", rng, level=40)),
        (tex(22), T2, "circles", "strip_1_8", occluders.strip_occluder(tex(22), SIZE_M, T2, 1 / 8, "top", rng, level=200)),
    ], note="1/8 of the inner side hidden from one side, border included", seed=3)
    T1, T2 = pose(0.85, 150, 20, (-95, 5), 45), pose(0.9, 250, 10, (95, -5), 160)
    scene("strip_1_4", [
        (tex(33), T1, "circles", "strip_1_4", occluders.strip_occluder(tex(33), SIZE_M, T1, 1 / 4, "bottom", rng, level=120)),
        (tex(48), T2, "circles", "strip_1_4", occluders.strip_occluder(tex(48), SIZE_M, T2, 1 / 4, "right", rng, level=60)),
    ], note="1/4 of the inner side hidden from one side, border included", seed=4)
    T1 = pose(0.9, 60, 20, (0, 0), 100)
    scene("strip_1_4_parity4", [
        (tex(11, 4), T1, "circles", "strip_1_4",
         occluders.strip_occluder(tex(11, 4), SIZE_M, T1, 1 / 4, "left", rng, level=180)),
    ], parity=4, note="parity 4, 1/4 strip", seed=5)

    # a blob on the data area: the square path, corrected by RS
    T1, T2 = pose(0.85, 10, 20, (-95, 0), 0), pose(0.85, 200, 25, (95, 0), 90)
    scene("blob", [
        (tex(2), T1, "square", "blob", occluders.blob_occluder(SIZE_M, T1, rng, 0.2, level=30)),
        (tex(29), T2, "square", "blob", occluders.blob_occluder(SIZE_M, T2, rng, 0.2, level=230)),
    ], note="blobs inside the data area (RS corrects them)", seed=6)

    # nothing to find: clutter; plain ArUco and AprilTag markers; an RS marker half gone
    scene("marker_free_clutter", [], note="clutter only", seed=7)
    aruco = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50)
    april = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    scene("other_families", [
        (raster.aruco_marker_texture(aruco, 3), pose(0.85, 10, 15, (-95, 0), 20), None, "none", None),
        (raster.aruco_marker_texture(april, 21, family="apriltag"), pose(0.85, -20, 20, (95, 0), 80), None, "none",
         None),
    ], note="OpenCV DICT_6X6_50 id 3 and AprilTag 36h11 id 21: not RS markers, nothing may be reported", seed=8)
    T1 = pose(0.9, 0, 10, (0, 0), 0)
    scene("too_occluded", [
        (tex(9), T1, None, "strip_5_8", occluders.strip_occluder(tex(9), SIZE_M, T1, 5 / 8, "left", rng, level=90)),
    ], note="5/8 of an RS marker hidden: not decodable, nothing may be reported", seed=9)

    # added with issue 13 (their own generator, so the frames above stay as they were)
    rng_new = np.random.default_rng(13)
    # a side and both its corners hidden by a long occluder (a rack upright, a pipe): three edges, two corners
    T1, T2 = pose(0.85, 25, 20, (-95, 0), 60), pose(0.85, -60, 25, (95, 5), 150)
    scene("side_corners", [
        (tex(14), T1, "circles", "side_1_8",
         occluders.side_occluder(tex(14), SIZE_M, T1, 1 / 8, "right", rng_new, level=50)),
        (tex(37), T2, "circles", "side_1_4",
         occluders.side_occluder(tex(37), SIZE_M, T2, 1 / 4, "bottom", rng_new, level=190)),
    ], note="a long occluder over one side and past both its corners (1/8 and 1/4 of the inner side)", seed=10)

    # occluded markers beside a clean one: all three are found in the same frame
    T1, T2, T3 = pose(0.9, 5, 15, (-120, -10), 30), pose(0.9, 40, 20, (0, 20), 100), pose(0.9, -25, 20, (120, -15), 200)
    scene("clean_beside_occluded", [
        (tex(4), T1, "square", "none", None),
        (tex(25), T2, "circles", "side_1_4", occluders.side_occluder(tex(25), SIZE_M, T2, 1 / 4, "left", rng_new, level=80)),
        (tex(42), T3, "circles", "corner", occluders.corner_occluder(tex(42), SIZE_M, T3, 0.25, 2, rng_new, level=160)),
    ], note="one clean marker and two occluded ones: the circles path runs beside the square path's finds", seed=11)

    # a 9 px linear smear (motion blur), as in the benchmark's motion_blur condition
    T1, T2 = pose(0.75, 15, 20, (-90, 0), 45), pose(0.75, -40, 15, (95, 0), 135)
    scene("motion_blur", [
        (tex(19), T1, "square", "none", None),
        (tex(46), T2, "square", "none", None),
    ], note="a 9 px linear smear at 30 degrees", seed=12,
       degradations=scenes.BASE_DEGRADATIONS.with_(motion_length_px=9.0, motion_angle_rad=math.radians(30)))

    # the same smear over a small marker (38 px: 5 px cells, the white gap ring closes and ArUco finds no quad)
    # beside a larger one: found on the frame deconvolved with the smear measured on the larger one
    T1, T2 = pose(0.62, 10, 15, (-90, -10), 40), pose(1.15, -35, 20, (95, 10), 120)
    scene("motion_blur_small", [
        (tex(19), T1, "square", "none", None),
        (tex(33), T2, "square", "none", None),
    ], note="a 9 px linear smear at 60 degrees over a 38 px marker beside a 67 px one", seed=21,
       degradations=scenes.BASE_DEGRADATIONS.with_(motion_length_px=9.0, motion_angle_rad=math.radians(60)))

    benchmark_crops()
    walk_crops()


def benchmark_crops() -> None:
    """Frames cut (400 x 300 around the markers named) from scenes of ``benchmarks/bench_detector.py`` (seed 2024)
    in which the detector once missed a marker; the truth is the benchmark renderer's."""
    sys.path.insert(0, str(HERE.parents[2] / "benchmarks"))
    import bench_detector as bench
    textures = bench.Textures()
    for name, condition, index, marker_ids, note in (
            ("dim_small", "low_light", 138, (1,),
             "a 33 px marker seen obliquely in a dim frame (mean gray 20, marker contrast 24): ArUco finds its quad "
             "only with the dim frame's lower threshold offset"),
            ("thin_oblique_blurred", "gaussian_blur", 36, (42,),
             "a thin oblique 40 px marker under blur: ArUco identifies it with corners 2 px off along its long "
             "sides, and it decodes only after the edges' wide pass"),
            ("round_blur", "gaussian_blur", 68, (30, 23),
             "a Gaussian blur: the 39 px marker's wide edges and no line smear send the square path over the frame "
             "again with a 7 px threshold window, which finds the small oblique one (the 15 px window closes its "
             "gap ring)"),
            ("noisy_small", "noise", 122, (36, 38),
             "grain of sd 12: the 15 px threshold window finds LEFT but breaks the quad of UP, small and oblique, "
             "up; the small_window pass over the noisy frame (7 px) finds it"),
            ("dim_oblique", "low_light", 20, (33,),
             "an oblique marker in a dim frame (mean gray about 20): found only by the small_window pass (7 px) "
             "with the dim frame's lower offset")):
        rendered = bench.render_family(textures, "rs", bench.scene_ids(2024, condition, index), condition, 2024, index)
        truths = [next(t for t in rendered.truths if t.marker_id == marker_id) for marker_id in marker_ids]
        write_crop(name, rendered.image, truths, np.mean([t.corners_px.mean(axis=0) for t in truths], axis=0),
                   {"note": note})


def walk_crops() -> None:
    """Frames cut (400 x 300 around the markers named) from ``benchmarks/bench_survey.py``'s 640x480 hall walk,
    found only by the survey's detector (``DetectorParams.for_footage``); the truth is the simulator's."""
    sys.path.insert(0, str(HERE.parents[2] / "benchmarks"))
    import bench_survey as bench
    from companion.sim import simulate
    simulator = simulate.Simulator(simulate.build_world(bench.load_map(bench.MAP_PATH)), bench.camera_model(640, 480),
                                   bench.handheld(bench.hall_walk()), bench.WALK_DEGRADATIONS, seed=11,
                                   occluder_count=bench.WALK_OCCLUDERS)
    for name, index, marker_ids, note in (
            ("walk_smeared_small", 247, (44, 19),
             "a frame of a hand-held walk: a 20 px marker smeared by about 2 px, in a frame that looks neither "
             "blurred, dim nor noisy; the usual 15 px threshold window closes its gap ring, the survey's detector "
             "reads every frame again with the 7 px window and finds it"),
            ("walk_smeared_deconvolved", 2075, (13, 14),
             "a frame of a hand-held walk: a 21 px marker beside a larger one, found only on the frame deconvolved "
             "with the smear measured on the larger one and read with the 7 px window (the survey's detector)"),):
        frame = simulator.render_frame(index, round(index * 1e9 / 4.0))
        truths = [next(t for t in frame.truths if t.marker_id == marker_id) for marker_id in marker_ids]
        write_crop(name, frame.image, truths, truths[-1].corners_px.mean(axis=0),
                   {"note": note, "params": "for_footage"})


def write_crop(name: str, image: np.ndarray, truths, centre_px: np.ndarray, fields: dict) -> None:
    """NAME.png, the W x H window of a parity-2 frame about centre_px (kept inside it), and NAME.json: the
    square-path markers ``truths`` in the window, then ``fields`` (note, params)."""
    height, width = image.shape
    x0, y0 = np.clip(np.round(centre_px - [W / 2, H / 2]), 0, [width - W, height - H]).astype(int)
    cv2.imwrite(str(HERE / f"{name}.png"), image[y0:y0 + H, x0:x0 + W])
    layout = MarkerLayout(2)
    markers = [{"symbol": layout.dictionary.symbol_of(t.marker_id), "id": t.marker_id,
                "corners": np.round(t.corners_px - [x0, y0], 3).tolist(), "path": "square", "occlusion": "none"}
               for t in truths]
    (HERE / f"{name}.json").write_text(json.dumps({"parity": 2, "markers": markers, **fields}, indent=1) + "\n")


if __name__ == "__main__":
    main()
