"""Road geometry of one scene: arc-length paths, the ego route (straights, bends, a junction) and crossing roads.

Everything is planar (z = 0) in the world frame of the scene, metres. A `Path` is a polyline sampled every
`STEP` metres with its heading; lanes, sidewalks and agent tracks are lateral offsets of a road's centreline.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

STEP = 0.25  # m between path samples
LANE_WIDTH = 3.5
SHOULDER = 2.2  # parking strip between the outer lane and the curb
SIDEWALK = 3.0


@dataclass
class Path:
    """A polyline parametrised by arc length `s` (m), with heading `yaw` (rad) at every sample."""

    xy: np.ndarray
    yaw: np.ndarray
    s: np.ndarray

    @staticmethod
    def from_points(xy: np.ndarray) -> Path:
        """Resample a dense polyline to uniform arc length and compute headings."""
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-6])
        xy = xy[keep]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        su = np.arange(0.0, s[-1] + 1e-9, STEP)
        pts = np.stack([np.interp(su, s, xy[:, 0]), np.interp(su, s, xy[:, 1])], axis=1)
        d = np.gradient(pts, axis=0)
        return Path(pts, np.unwrap(np.arctan2(d[:, 1], d[:, 0])), su)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (x, y) and heading at arc length(s) `s`; beyond the ends the path extends straight."""
        s = np.asarray(s, dtype=float)
        sc = np.clip(s, 0.0, self.length)
        x = np.interp(sc, self.s, self.xy[:, 0])
        y = np.interp(sc, self.s, self.xy[:, 1])
        yaw = np.interp(sc, self.s, self.yaw)
        over = s - sc
        return x + over * np.cos(yaw), y + over * np.sin(yaw), yaw

    def offset(self, d: float) -> Path:
        """The parallel path `d` metres to the left (negative: right)."""
        n = np.stack([-np.sin(self.yaw), np.cos(self.yaw)], axis=1)
        return Path.from_points(self.xy + d * n)

    def reversed(self) -> Path:
        return Path.from_points(self.xy[::-1].copy())

    def curvature(self) -> np.ndarray:
        """Signed curvature (1/m, left positive) at every sample."""
        return np.gradient(self.yaw, STEP)

    def project(self, xy: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """Arc length and signed lateral offset (left positive) of points (N, 2) on their nearest sample."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        sub_x, sub_y = np.ascontiguousarray(self.xy[::8].T)
        idx = np.empty(len(xy), dtype=int)
        for i in range(0, len(xy), chunk):  # squared distances as dx * dx + dy * dy: einsum's sum, several x faster
            dx, dy = xy[i:i + chunk, 0, None] - sub_x, xy[i:i + chunk, 1, None] - sub_y
            dx *= dx
            dy *= dy
            dx += dy
            idx[i:i + chunk] = dx.argmin(1) * 8
        rel = xy - self.xy[idx]
        c, s = np.cos(self.yaw[idx]), np.sin(self.yaw[idx])
        return self.s[idx] + rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c


@dataclass
class Road:
    """A two-way road: centreline, lanes per direction; the carriageway includes a parking shoulder."""

    center: Path
    lanes: int

    @property
    def half_width(self) -> float:
        return self.lanes * LANE_WIDTH + SHOULDER


@dataclass
class Junction:
    center: np.ndarray  # (2,)
    heading: float  # heading of the approach
    half: float  # half size of the paved junction square
    turn: str  # "left", "right" or "straight": what the route does here
    s_route: float  # arc length of the junction centre along the route centreline


@dataclass
class RoadNet:
    route: Road
    others: list[Road]
    junctions: list[Junction] = field(default_factory=list)

    @property
    def roads(self) -> list[Road]:
        return [self.route, *self.others]


def _arc(p: np.ndarray, h: float, radius: float, angle: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Dense points of an arc starting at `p` with heading `h`, turning by `angle` (left positive)."""
    n = max(int(abs(angle) * radius / 0.2), 2)
    sign = np.sign(angle)
    c = p + sign * radius * np.array([-np.sin(h), np.cos(h)])
    phis = h - sign * np.pi / 2 + np.linspace(0.0, angle, n)
    pts = c + radius * np.stack([np.cos(phis), np.sin(phis)], axis=1)
    return pts, pts[-1], h + angle


def _straight(p: np.ndarray, h: float, length: float) -> tuple[np.ndarray, np.ndarray, float]:
    n = max(int(length / 0.5), 2)
    t = np.linspace(0.0, length, n)[:, None]
    pts = p + t * np.array([np.cos(h), np.sin(h)])
    return pts, pts[-1], h


def build_roads(rng: np.random.Generator, total: float = 560.0) -> RoadNet:
    """A route of straights and bends with at most one junction, plus the junction's crossing road."""
    lanes = int(rng.choice([1, 2], p=[0.55, 0.45]))
    hw = lanes * LANE_WIDTH + SHOULDER
    p, h = np.zeros(2), 0.0
    parts: list[np.ndarray] = []
    length = 0.0
    has_junction = rng.random() < 0.7
    junction_at = rng.uniform(120.0, 230.0) if has_junction else np.inf
    junctions_spec: list[tuple[np.ndarray, float, str, float, float]] = []
    while length < total:
        if length + 40.0 >= junction_at and not junctions_spec:
            turn = str(rng.choice(["left", "right", "straight"], p=[0.36, 0.36, 0.28]))
            radius = rng.uniform(hw + 5.0, hw + 9.0)
            center = p + radius * np.array([np.cos(h), np.sin(h)])
            junctions_spec.append((center.copy(), h, turn, length + radius, radius))
            if turn == "straight":
                pts, p, h = _straight(p, h, 2 * radius)
            else:
                pts, p, h = _arc(p, h, radius, np.pi / 2 * (1 if turn == "left" else -1))
        elif not parts or rng.random() < 0.55:
            pts, p, h = _straight(p, h, rng.uniform(30.0, 90.0) if parts else 70.0)
        else:
            if rng.random() < 0.6:  # a bend the command shows (more than 2 m of lateral offset within 3 s)
                radius, angle = rng.uniform(35.0, 110.0), rng.uniform(0.35, 1.1) * rng.choice([-1, 1])
            else:  # a gentle bend the command mostly leaves at STRAIGHT: only the cameras show it
                radius, angle = rng.uniform(120.0, 320.0), rng.uniform(0.25, 0.6) * rng.choice([-1, 1])
            pts, p, h = _arc(p, h, radius, angle)
        parts.append(pts)
        length += float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    route = Road(Path.from_points(np.concatenate(parts)), lanes)
    net = RoadNet(route, [])
    for center, hin, turn, s_j, radius in junctions_spec:
        direction = np.array([-np.sin(hin), np.cos(hin)])
        cross = np.stack([center - 90.0 * direction, center + 90.0 * direction])
        net.others.append(Road(Path.from_points(_densify(cross)), lanes))
        if turn != "straight":
            ahead = np.stack([center, center + 90.0 * np.array([np.cos(hin), np.sin(hin)])])
            net.others.append(Road(Path.from_points(_densify(ahead)), lanes))
        net.junctions.append(Junction(center, hin, max(hw, radius) + 1.0, turn, s_j))
    return net


def _densify(pts: np.ndarray) -> np.ndarray:
    n = max(int(np.linalg.norm(pts[-1] - pts[0]) / 0.5), 2)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return pts[0] + t * (pts[-1] - pts[0])


def distance_to_roads(net: RoadNet, xy: np.ndarray) -> np.ndarray:
    """Distance (m) of points (N, 2) outside the nearest carriageway edge (negative inside a road)."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    best = np.full(len(xy), np.inf)
    for road in net.roads:
        sub = road.center.xy[::8]
        d = np.sqrt(((xy[:, None, :] - sub[None, :, :]) ** 2).sum(-1)).min(1) - road.half_width
        best = np.minimum(best, d)
    for j in net.junctions:
        c, s = np.cos(j.heading), np.sin(j.heading)
        rel = xy - j.center
        uv = np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], axis=1)
        best = np.minimum(best, np.abs(uv).max(1) - j.half)
    return best


def in_junction(net: RoadNet, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """True for points (N, 2) inside a paved junction square (axis-aligned to the approach heading)."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    inside = np.zeros(len(xy), dtype=bool)
    for j in net.junctions:
        c, s = np.cos(j.heading), np.sin(j.heading)
        rel = xy - j.center
        u, v = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        inside |= (np.abs(u) < j.half + margin) & (np.abs(v) < j.half + margin)
    return inside


CHUNK_M = 40.0  # m of centreline per carriageway polygon
CAP_SEGMENTS = 48  # segments of the half disc at each end of a road (0.005 m chord error at 9.2 m)


def drivable_polygons(net: RoadNet) -> list[np.ndarray]:
    """The paved carriageways and junction squares as simple counter-clockwise polygons (K, 2), world metres.

    Their union is what `texture._paint_roads` paints as asphalt: each road's centreline polyline buffered by
    its half width (OpenCV draws a thick polyline with round joins and ends, so the painted band is that
    buffer) and each junction square. A road is cut into pieces of `CHUNK_M` metres: each piece is its two
    edges offset along the sample normals, closed straight across where it meets the next piece (both share
    that sample, hence that edge) and by a half disc at the road's two ends. Every bend is wider than the half
    width, so no offset edge folds over itself. Sidewalks, curbs and the verge are outside.
    """
    out: list[np.ndarray] = []
    step = max(round(CHUNK_M / STEP), 2)
    half_disc = np.linspace(0.0, np.pi, CAP_SEGMENTS + 1)[1:-1]
    for road in net.roads:
        c, hw = road.center, road.half_width
        n = len(c.xy)
        for a in range(0, max(n - 1, 1), step):
            b = min(a + step, n - 1)
            xy, yaw = c.xy[a:b + 1], c.yaw[a:b + 1]
            normal = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
            left, right = xy + hw * normal, xy - hw * normal
            ring = [right]
            if b == n - 1:  # the road's far end: right -> round -> left
                phi = yaw[-1] - np.pi / 2 + half_disc
                ring.append(xy[-1] + hw * np.stack([np.cos(phi), np.sin(phi)], axis=1))
            ring.append(left[::-1])
            if a == 0:  # the road's near end: left -> round -> right
                phi = yaw[0] + np.pi / 2 + half_disc
                ring.append(xy[0] + hw * np.stack([np.cos(phi), np.sin(phi)], axis=1))
            out.append(np.concatenate(ring))
    for j in net.junctions:
        c, s = np.cos(j.heading), np.sin(j.heading)
        u, v = np.array([c, s]), np.array([-s, c])
        out.append(np.array([j.center + a * j.half * u + b * j.half * v
                             for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]))
    return out
