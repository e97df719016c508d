"""3D models as oriented boxes ("parts") with per-face colours and flat decals (windows, lights, plates).

A part is (cx, cy, yaw, z0, z1, length, width) in the world frame; faces are ordered +x (front), -x (back),
+y (left), -y (right), +z (top). Decals are world-frame quads drawn over the face they belong to.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .lights import DARK, GREEN, HEAD_Z, HOUSING, LIT, RED, YELLOW

GLASS = (45, 55, 70)
TYRE = (28, 28, 30)


@dataclass
class Parts:
    boxes: list[tuple] = field(default_factory=list)  # (cx, cy, yaw, z0, z1, l, w)
    colours: list[np.ndarray] = field(default_factory=list)  # (5, 3) per box
    decals: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)

    def add(self, cx, cy, yaw, z0, z1, l, w, colour, faces: dict[int, tuple | np.ndarray] | None = None) -> int:
        col = np.tile(np.asarray(colour, np.float32), (5, 1))
        for f, c in (faces or {}).items():
            col[f] = c
        self.boxes.append((cx, cy, yaw, z0, z1, l, w))
        self.colours.append(col)
        return len(self.boxes) - 1

    def decal(self, part: int, face: int, quads_local: np.ndarray, colours: np.ndarray) -> None:
        """Attach quads given in the part's local frame (x along, y left, z up; (n, 4, 3))."""
        cx, cy, yaw = self.boxes[part][:3]
        c, s = np.cos(yaw), np.sin(yaw)
        q = np.asarray(quads_local, np.float64).reshape(-1, 4, 3)
        w = np.empty_like(q)
        w[..., 0] = cx + c * q[..., 0] - s * q[..., 1]
        w[..., 1] = cy + s * q[..., 0] + c * q[..., 1]
        w[..., 2] = q[..., 2]
        faces = np.full(len(q), face)
        cols = np.asarray(colours, np.float32).reshape(-1, 3)
        if part in self.decals:
            f0, q0, c0 = self.decals[part]
            faces, w, cols = np.concatenate([f0, faces]), np.concatenate([q0, w]), np.concatenate([c0, cols])
        self.decals[part] = (faces, w, cols)


def _local(cx, cy, yaw, dx, dy):
    c, s = np.cos(yaw), np.sin(yaw)
    return cx + c * dx - s * dy, cy + s * dx + c * dy


def _rect_x(x, y0, y1, z0, z1):
    """A quad on a plane of constant x."""
    return [[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]]


def _rect_y(y, x0, x1, z0, z1):
    return [[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]]


def _wheels(p: Parts, cx, cy, yaw, l, w, positions=(0.31, -0.31), r=0.33):
    for fx in positions:
        for sy in (-1, 1):
            x, y = _local(cx, cy, yaw, fx * l, sy * (w / 2 - 0.11))
            p.add(x, y, yaw, 0.0, 2 * r, 2 * r, 0.24, TYRE)


def _lights(p: Parts, part, l, w, h, braking: bool, z=(0.42, 0.52)):
    tail = (255, 40, 30) if braking else (125, 22, 20)
    quads = [_rect_x(-l / 2 - 0.02, sy * (w / 2 - 0.05), sy * (w / 2 - 0.38), z[0] * h, z[1] * h) for sy in (-1, 1)]
    plate = _rect_x(-l / 2 - 0.02, -0.26, 0.26, 0.30 * h, 0.38 * h)
    p.decal(part, 1, np.array(quads + [plate]), np.array([tail, tail, (225, 225, 215)]))
    heads = [_rect_x(l / 2 + 0.02, sy * (w / 2 - 0.08), sy * (w / 2 - 0.38), z[0] * h, z[1] * h) for sy in (-1, 1)]
    grille = _rect_x(l / 2 + 0.02, -0.3, 0.3, 0.3 * h, 0.42 * h)
    p.decal(part, 0, np.array(heads + [grille]), np.array([(240, 235, 200), (240, 235, 200), (35, 35, 38)]))


def vehicle(p: Parts, kind, x, y, yaw, size, colour, braking) -> None:
    """Car, truck or bus: body, cabin or cargo box, wheels, lights, windows."""
    l, w, h = size
    if kind == "car":
        body = p.add(x, y, yaw, 0.28, 0.58 * h, l, w, colour)
        cx, cy = _local(x, y, yaw, -0.06 * l, 0.0)
        p.add(cx, cy, yaw, 0.58 * h, h, 0.52 * l, 0.86 * w, GLASS, {4: colour})
        _lights(p, body, l, w, h, braking, (0.28, 0.36) if h < 1.6 else (0.42, 0.52))
        _wheels(p, x, y, yaw, l, w)
    elif kind == "truck":
        cx, cy = _local(x, y, yaw, -0.14 * l, 0.0)
        cargo = p.add(cx, cy, yaw, 0.6, h, 0.72 * l, w, (225, 225, 220))
        _lights(p, cargo, 0.72 * l, w, h, braking, (0.2, 0.26))
        cx, cy = _local(x, y, yaw, 0.37 * l, 0.0)
        cab = p.add(cx, cy, yaw, 0.5, 0.8 * h, 0.26 * l, w, colour)
        p.decal(cab, 0, np.array([_rect_x(0.13 * l + 0.02, -w / 2 + 0.15, w / 2 - 0.15, 0.55 * h, 0.76 * h)]),
                np.array([GLASS]))
        _wheels(p, x, y, yaw, l, w, (0.36, -0.2, -0.36), 0.45)
    else:
        bus = p.add(x, y, yaw, 0.35, h, l, w, colour)
        band = [_rect_y(sy * (w / 2 + 0.02), -0.45 * l, 0.42 * l, 0.5 * h, 0.82 * h) for sy in (-1, 1)]
        p.decal(bus, 2, np.array(band[1:]), np.array([GLASS]))
        p.decal(bus, 3, np.array(band[:1]), np.array([GLASS]))
        p.decal(bus, 0, np.array([_rect_x(l / 2 + 0.02, -w / 2 + 0.1, w / 2 - 0.1, 0.45 * h, 0.88 * h)]),
                np.array([GLASS]))
        _lights(p, bus, l, w, h, braking, (0.2, 0.28))
        _wheels(p, x, y, yaw, l, w, (0.33, -0.3), 0.5)


def person(p: Parts, x, y, yaw, size, colour, cyclist: bool) -> None:
    """Pedestrian (legs, torso, head) or cyclist (bicycle frame, wheels, rider)."""
    l, w, h = size
    skin = (205, 165, 130)
    if cyclist:
        p.add(x, y, yaw, 0.35, 0.8, 1.5, 0.08, (30, 30, 32))
        for fx in (-0.55, 0.55):
            wx, wy = _local(x, y, yaw, fx, 0.0)
            p.add(wx, wy, yaw, 0.0, 0.68, 0.68, 0.05, TYRE)
        p.add(x, y, yaw, 0.85, 0.82 * h, 0.4, 0.42, colour)
        p.add(x, y, yaw, 0.84 * h, h, 0.22, 0.2, skin)
        return
    p.add(x, y, yaw, 0.0, 0.47 * h, 0.24, 0.34, (40, 40, 55))
    p.add(x, y, yaw, 0.47 * h, 0.86 * h, 0.28, 0.46, colour)
    p.add(x, y, yaw, 0.86 * h, h, 0.22, 0.2, skin)


def building(p: Parts, prop, rng) -> None:
    """A block with floors of windows on every side and a darker roof."""
    l, w, h = prop.size
    x, y = prop.xy
    col = np.asarray(prop.colour, np.float32)
    part = p.add(x, y, prop.yaw, 0.0, h, l, w, col, {4: col * 0.6})
    floors = max(1, int(h / 3.2))
    for face, (span, fixed, rect) in enumerate(((w, l / 2 + 0.03, _rect_x), (w, -l / 2 - 0.03, _rect_x),
                                                (l, w / 2 + 0.03, _rect_y), (l, -w / 2 - 0.03, _rect_y))):
        bays = max(1, int(span / 3.0))
        centres = (np.arange(bays) + 0.5) * span / bays - span / 2
        quads = [rect(fixed, c - 0.7, c + 0.7, f * 3.2 + 0.9, f * 3.2 + 2.4) for f in range(floors) for c in centres]
        shade = rng.uniform(0.6, 1.3, size=(len(quads), 1))
        p.decal(part, face, np.array(quads), np.clip(np.array(GLASS) * shade + [0, 5, 15], 0, 255))


def tree(p: Parts, prop, rng) -> None:
    x, y = prop.xy
    h, crown = prop.size[2], prop.extra["crown"]
    p.add(x, y, 0.0, 0.0, 0.5 * h, 0.35, 0.35, prop.colour)
    green = np.array([50, 95, 40]) * rng.uniform(0.75, 1.25)
    p.add(x, y, 0.3, 0.4 * h, h, 2 * crown, 2 * crown, green, {4: green * 1.1})
    p.add(x, y, 1.085, 0.45 * h, 0.95 * h, 2 * crown, 2 * crown, green * 0.9, {4: green})


def pole(p: Parts, prop, rng) -> None:
    x, y = prop.xy
    p.add(x, y, prop.yaw, 0.0, prop.size[2], 0.18, 0.18, prop.colour)
    p.add(x, y, prop.yaw, prop.size[2], prop.size[2] + 0.25, 0.7, 0.35, (60, 60, 62))


def light_parts(p: Parts, net, lights, step: int, dt: float) -> None:
    """Add each traffic light's pole, mast arm and head (`lights.TrafficLight`), its lamps lit by its state at sim
    `step` (`dt` s each)."""
    for light in lights:
        traffic_light(p, light.pole(net), light.head(net), light.state_at(step * dt))


def traffic_light(p: Parts, pole_at, head_at, state: str) -> None:
    """A traffic light on a mast arm: pole on the curb, arm over the lanes, head facing the approaching traffic with
    three lamps (red, yellow, green from the top), the one of `state` lit (`lights.LIT`, `lights.DARK`)."""
    px, py, pyaw = pole_at
    hx, hy, hyaw = head_at
    top = HEAD_Z[1] + 0.2
    p.add(px, py, pyaw, 0.0, top, 0.22, 0.22, (95, 95, 100))
    span = float(np.hypot(hx - px, hy - py)) + 0.2
    p.add((px + hx) / 2, (py + hy) / 2, float(np.arctan2(hy - py, hx - px)), top - 0.2, top, span, 0.16,
          (95, 95, 100))
    l, w = 0.4, 0.8
    head = p.add(hx, hy, hyaw, HEAD_Z[0], HEAD_Z[1], l, w, HOUSING)
    step = (HEAD_Z[1] - HEAD_Z[0]) / 3
    lamps = [_rect_x(l / 2 + 0.02, -0.28, 0.28, HEAD_Z[0] + (2 - i) * step + 0.04, HEAD_Z[0] + (3 - i) * step - 0.04)
             for i in range(3)]
    colours = [LIT[c] if c == state else DARK[c] for c in (RED, YELLOW, GREEN)]
    p.decal(head, 0, np.array(lamps), np.array(colours, dtype=np.float64))
