"""`LaneView._distances` and `motion.path_distance`, written per coordinate for speed (issue 23), give the bits
of the vector formulas they replaced (a dot product and `np.linalg.norm` over a length-2 axis): DDC, LK and the
out-of-lane test, and so every PDMS and EPDMS, stay as they were, whatever the segments (degenerate ones
included), points and scale; `LaneView._near`'s bisection finds the segments the scan of every end found."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.metrics.pdms.lanes import LaneView
from pytest_drivedegrade.metrics.pdms.motion import path_distance


def vector_formula(start: np.ndarray, end: np.ndarray, pts: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """The distances as the suite computed them before (spec 4.1.0 to 4.2.0)."""
    a, ab = start[segments], end[segments] - start[segments]
    t = np.clip(((pts[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a[None] + t[..., None] * ab[None] - pts[:, None], axis=-1)


def view(start: np.ndarray, end: np.ndarray) -> LaneView:
    d = end - start
    return LaneView(start, end, np.arctan2(d[:, 1], d[:, 0]), np.zeros(len(start), int), (None,), ())


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), segments=st.integers(1, 300), points=st.integers(1, 40),
       log_scale=st.floats(-3.0, 4.0), degenerate=st.floats(0.0, 0.5))
def test_distances_equal_the_vector_formula_bit_for_bit(seed, segments, points, log_scale, degenerate):
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    start = rng.normal(0.0, scale, (segments, 2))
    end = start + rng.normal(0.0, scale, (segments, 2)) * (rng.random((segments, 1)) >= degenerate)
    pts = rng.normal(0.0, scale, (points, 2))
    chosen = np.flatnonzero(rng.random(segments) < 0.7)
    if not len(chosen):
        chosen = np.arange(segments)
    got = view(start, end)._distances(pts, chosen)
    assert got.shape == (points, len(chosen))
    assert got.tobytes() == vector_formula(start, end, pts, chosen).tobytes()


def test_known_distances_to_a_segment():
    lanes = view(np.array([[0.0, 0.0], [5.0, 5.0]]), np.array([[10.0, 0.0], [5.0, 5.0]]))  # the second: a point
    pts = np.array([[5.0, 3.0], [-3.0, 4.0], [13.0, -4.0], [5.0, 5.0]])
    got = lanes._distances(pts, np.array([0, 1]))
    np.testing.assert_array_equal(got[:, 0], [3.0, 5.0, 5.0, 5.0])  # foot inside, before the start, past the end
    np.testing.assert_array_equal(got[:, 1], [2.0, np.hypot(8.0, 1.0), np.hypot(8.0, 9.0), 0.0])


def near_by_scan(start: np.ndarray, end: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    """The near segments as the suite found them before (every end tested against the box)."""
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    return np.flatnonzero(((start >= lo) & (start <= hi)).all(1) | ((end >= lo) & (end <= hi)).all(1))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), segments=st.integers(1, 400), points=st.integers(1, 40),
       grid=st.booleans(), margin=st.sampled_from([0.0, 0.5, 10.0]))
def test_near_segments_by_bisection_equal_the_scan_of_every_end(seed, segments, points, grid, margin):
    """Ends exactly on the box's edges (a coarse grid puts many there), shared ends and NaN ends included."""
    rng = np.random.default_rng(seed)
    draw = (lambda shape: rng.integers(-20, 21, shape).astype(float)) if grid else \
        (lambda shape: rng.normal(0.0, 15.0, shape))
    start = draw((segments, 2))
    end = np.where(rng.random((segments, 1)) < 0.3, np.roll(start, -1, axis=0), draw((segments, 2)))
    end[rng.random(segments) < 0.05] = np.nan
    pts = draw((points, 2))
    got = view(start, end)._near(pts, margin)
    want = near_by_scan(start, end, pts, margin)
    assert got.dtype.kind == "i" and got.tolist() == want.tolist()


def test_near_segments_of_a_known_box():
    start = np.array([[0.0, 0.0], [20.0, 0.0], [10.0, 10.0], [-5.0, 0.0]])
    end = np.array([[5.0, 0.0], [30.0, 0.0], [10.0, 11.0], [0.0, 1.0]])
    lanes = view(start, end)
    assert lanes._near(np.array([[1.0, 0.0], [2.0, 0.0]]), 0.0).tolist() == []  # no end inside [1, 2] x [0, 0]
    assert lanes._near(np.array([[1.0, 0.0], [2.0, 0.0]]), 1.0).tolist() == [0, 3]  # (0, 0) and (0, 1) on the edges
    assert lanes._near(np.array([[10.0, 10.5]]), 0.5).tolist() == [2]
    assert view(np.zeros((0, 2)), np.zeros((0, 2)))._near(np.zeros((1, 2)), 10.0).tolist() == []


def path_distance_vector_formula(path: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """`motion.path_distance` as the suite computed it before issue 23's second pass."""
    a, b = path[:-1], path[1:]
    ab = b - a
    t = ((pts[:, None, :] - a[None]) * ab[None]).sum(-1) / (ab**2).sum(1)[None]
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    lo[0], hi[-1] = -np.inf, np.inf
    t = np.clip(t, lo[None], hi[None])
    return np.linalg.norm(a[None] + t[..., None] * ab[None] - pts[:, None, :], axis=-1).min(1)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), vertices=st.integers(2, 12), points=st.integers(1, 130),
       log_scale=st.floats(-3.0, 4.0))
def test_path_distance_equals_the_vector_formula_bit_for_bit(seed, vertices, points, log_scale):
    """The expert's path (its points de-duplicated, so no zero-length segment) against the ego box's corners."""
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    path = np.cumsum(rng.normal(0.0, scale, (vertices, 2)) + 1e-3 * scale, axis=0)
    pts = rng.normal(0.0, 3 * scale, (points, 2))
    got = path_distance(path, pts)
    assert got.shape == (points,)
    assert got.tobytes() == path_distance_vector_formula(path, pts).tobytes()


def test_path_distance_continues_the_end_segments_straight():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    pts = np.array([[-5.0, 3.0], [5.0, -2.0], [13.0, 20.0], [12.0, 5.0]])
    np.testing.assert_array_equal(path_distance(path, pts), [3.0, 2.0, 3.0, 2.0])


def random_rings(rng: np.random.Generator, count: int, grid: bool) -> list[np.ndarray]:
    """Star-shaped rings around random centres (a few self-touching on a coarse grid), some of one or two
    vertices (no edges), some empty."""
    rings = []
    for _ in range(count):
        n = int(rng.choice([0, 1, 2, 3, 4, 7, 12]))
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radius = rng.uniform(1.0, 8.0, n)
        ring = rng.uniform(-10, 10, 2) + np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)
        rings.append(np.round(ring) if grid else ring)
    return rings


def ring_one_point_at_a_time(ring: np.ndarray, pts: np.ndarray) -> list[bool]:
    """The even-odd test as `maps.RingIndex` made it before issue 23's second pass: the points in the ring's
    bounding box, each against every edge (half-open straddle, crossing to the right of the point)."""
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
    out = []
    for px, py in pts.tolist():
        boxed = len(ring) >= 3 and ring[:, 0].min() <= px <= ring[:, 0].max() and \
            ring[:, 1].min() <= py <= ring[:, 1].max()
        if not boxed:
            out.append(False)
            continue
        x0, y0 = ring[:, 0], ring[:, 1]
        x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
        e = np.flatnonzero((y0 > py) != (y1 > py))
        t = (py - y0[e]) / (y1[e] - y0[e])
        out.append(int(np.count_nonzero(px < x0[e] + t * (x1[e] - x0[e]))) % 2 == 1)
    return out


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(0, 12), points=st.integers(0, 60), grid=st.booleans())
def test_a_ring_set_and_a_ring_index_contain_what_the_edge_by_edge_test_does(seed, count, points, grid):
    """Points on vertices and edges (the coarse grid) included: the same bits as testing each point against each
    edge, for any subset of the rings in any order, and for one ring at a time (`RingIndex`)."""
    from pytest_drivedegrade.data.maps import RingIndex, RingSet

    rng = np.random.default_rng(seed)
    rings = random_rings(rng, count, grid)
    pts = rng.integers(-18, 19, (points, 2)).astype(float) if grid else rng.uniform(-18, 18, (points, 2))
    chosen = rng.permutation(count)[: rng.integers(0, count + 1)] if count else np.zeros(0, int)
    got = RingSet(rings).contains(pts, chosen)
    assert got.shape == (points, len(chosen))
    for j, k in enumerate(chosen.tolist()):
        want = ring_one_point_at_a_time(rings[k], pts)
        assert got[:, j].tolist() == want
        assert RingIndex(rings[k]).contains(pts).tolist() == want


def query_one_ring_at_a_time(lanes: LaneView, xy: np.ndarray, heading: np.ndarray) -> tuple[list, list, list]:
    """`LaneView.query` as the suite computed it before (each near lane's polygon tested alone)."""
    from pytest_drivedegrade.metrics.pdms.lanes import NEAR_M

    def _wrap(angle: np.ndarray) -> np.ndarray:
        return (angle + np.pi) % (2 * np.pi) - np.pi

    pts, head = xy, heading
    near = near_by_scan(lanes.start, lanes.end, pts, NEAR_M)
    dist = lanes._distances(pts, near) if len(near) else np.zeros((len(pts), 0))
    along = np.abs(_wrap(lanes.yaw[near][None, :] - head[:, None])) < np.pi / 2
    deviation = np.where(along, dist, np.inf).min(axis=1) if len(near) else np.full(len(pts), np.inf)
    along_any = np.zeros(len(pts), bool)
    lane_of = lanes.lane[near]
    for k in np.unique(lane_of).tolist():
        if lanes.polygons[k] is None:
            continue
        inside = np.array(ring_one_point_at_a_time(lanes.polygons[k], pts), dtype=bool)
        if not inside.any():
            continue
        columns = np.flatnonzero(lane_of == k)
        seg = near[columns[dist[:, columns].argmin(axis=1)]]
        along_any |= inside & (np.abs(_wrap(lanes.yaw[seg] - head)) < np.pi / 2)
    junction = np.zeros(len(pts), bool)
    for ring in lanes.intersections:
        junction |= ring_one_point_at_a_time(ring, pts)
    return deviation.tolist(), (~along_any).tolist(), junction.tolist()  # off every lane: oncoming (NAVSIM)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 10), states=st.integers(1, 31), grid=st.booleans())
def test_the_lane_query_equals_testing_each_lane_polygon_alone(seed, count, states, grid):
    rng = np.random.default_rng(seed)
    rings = random_rings(rng, count, grid)
    centrelines = [ring[:: max(1, len(ring) // 3)] if len(ring) >= 2 else rng.uniform(-10, 10, (2, 2))
                   for ring in rings]
    polygons = [None if rng.random() < 0.2 else ring for ring in rings]
    lanes = LaneView.of_centrelines(centrelines, polygons, [r for r in random_rings(rng, 2, grid) if len(r) >= 3])
    xy = rng.uniform(-15, 15, (states, 2))
    heading = rng.uniform(-4.0, 4.0, states)
    q = lanes.query(xy, heading)
    assert (q.deviation.tolist(), q.oncoming.tolist(), q.in_intersection.tolist()) == \
        query_one_ring_at_a_time(lanes, xy, heading)


EDGES = [0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -2 * np.pi, 3 * np.pi, -3 * np.pi, np.nextafter(np.pi, 0),
         np.nextafter(-np.pi, 0), np.nextafter(3 * np.pi, 0), np.nextafter(-3 * np.pi, 0), 1e-300, -1e-300, 5e-324]


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.integers(0, 400), spread=st.sampled_from([1.0, 3.0, 3.2, 10.0, 1e6]),
       edges=st.booleans(), odd=st.sampled_from([None, np.nan, np.inf, -np.inf]))
def test_wrap_angle_has_the_bits_of_numpys_remainder(seed, size, spread, edges, odd):
    """Angles within a turn of the range take the fast path, the others numpy's remainder: the same bits either
    way, the zeros' signs included (-pi, pi and 3 pi exactly, their neighbours, subnormals, NaN and inf)."""
    from pytest_drivedegrade.data.geometry import wrap_angle

    rng = np.random.default_rng(seed)
    a = rng.uniform(-spread * np.pi, spread * np.pi, size)
    if edges and size:
        a[rng.integers(0, size, min(size, 20))] = rng.choice(EDGES, min(size, 20))
    if odd is not None and size:
        a[rng.integers(0, size)] = odd
    with np.errstate(invalid="ignore"):  # inf has no remainder: NaN, with numpy's warning, on both sides
        got, want = wrap_angle(a), (a + np.pi) % (2 * np.pi) - np.pi
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        assert wrap_angle(a.reshape(-1, 1)).shape == (size, 1)
        assert float(wrap_angle(2.5 * np.pi)) == float((2.5 * np.pi + np.pi) % (2 * np.pi) - np.pi)
        f32 = a.astype(np.float32)
        assert wrap_angle(f32).tobytes() == ((f32 + np.pi) % (2 * np.pi) - np.pi).tobytes()


def of_map_transforming_every_lane(lane_map, pose, radius: float) -> LaneView:
    """`LaneView.of_map` as the suite computed it before issue 23's third pass: every lane and junction of the
    map turned into the ego frame, then kept when its box meets [-radius, radius]^2."""
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)

    def local(xy):
        d = np.asarray(xy, dtype=np.float64)[:, :2] - [x, y]
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)

    def near(xy):
        return bool(len(xy)) and bool(((xy.min(0) <= radius) & (xy.max(0) >= -radius)).all())

    lanes = [(local(lane.centreline), None if lane.polygon is None else local(lane.polygon.exterior))
             for lane in lane_map.lanes if len(lane.centreline)]
    lanes = [(cl, poly) for cl, poly in lanes if near(cl)]
    junctions = [local(a.polygon.exterior) for a in lane_map.road_segments if a.is_intersection]
    return LaneView.of_centrelines([cl for cl, _ in lanes], [p for _, p in lanes], [j for j in junctions if near(j)])


def view_bytes(v: LaneView) -> list[bytes]:
    return [np.ascontiguousarray(a).tobytes() for a in (v.start, v.end, v.yaw, v.lane, *v.intersections)] + \
        [b"-" if p is None else np.ascontiguousarray(p).tobytes() for p in v.polygons]


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), lanes=st.integers(0, 40), spread=st.sampled_from([30.0, 150.0, 2000.0]),
       radius=st.sampled_from([5.0, 80.0]), far=st.booleans())
def test_lanes_skipped_by_their_boxes_are_the_lanes_no_ego_frame_box_would_keep(seed, lanes, spread, radius, far):
    """`of_map` skips a lane whose global box, turned into the ego frame, misses the window: the same view, byte
    for byte, as turning every lane and junction and testing each (long lanes, lanes just at the window's edge,
    empty centrelines, junctions and other road segments among them)."""
    from pytest_drivedegrade.data.maps import DrivableArea, Lane, LaneMap, MapArea, MapPolygon

    rng = np.random.default_rng(seed)
    origin = rng.uniform(-5e5, 5e5, 2) if far else np.zeros(2)
    pose = (*(origin + rng.uniform(-spread, spread, 2)), float(rng.uniform(-4.0, 4.0)))

    def polyline() -> np.ndarray:
        n = int(rng.integers(0, 30)) if rng.random() < 0.9 else 0
        start = origin + rng.uniform(-spread, spread, 2)
        steps = rng.normal(0.0, rng.choice([0.5, 5.0, 40.0]), (n, 2))
        xy = start + np.cumsum(steps, axis=0)
        return np.column_stack([xy, rng.uniform(-np.pi, np.pi, n)])

    made = [Lane(f"l{k}", None if rng.random() < 0.3 else MapPolygon(polyline()[:, :2]), polyline())
            for k in range(lanes)]
    areas = tuple(MapArea(f"a{k}", MapPolygon(polyline()[:, :2]), bool(rng.random() < 0.7)) for k in range(8))
    lane_map = LaneMap("somewhere", tuple(made), (), (), (), areas, DrivableArea([]))
    got = LaneView.of_map(lane_map, pose, radius)
    assert view_bytes(got) == view_bytes(of_map_transforming_every_lane(lane_map, pose, radius))
