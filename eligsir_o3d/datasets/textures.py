"""Procedural textures of the synthetic room: albedo as a function of a surface point (object frame, metres).

Each factory returns ``texture(points [M, 3], normals [M, 3]) -> rgb [M, 3]`` in [0, 1]; normals are unit and
face the viewer. The patterns (checkers, stripes, gradients, value noise, hard edges) give photometric
optimisation structure at several scales.
"""

from __future__ import annotations

import numpy as np


class ValueNoise:
    """Smooth 3D value noise on a periodic random lattice (seeded), fractal sums via :meth:`fbm`."""

    def __init__(self, rng: np.random.Generator, size: int = 32) -> None:
        self.size = size
        self.table = rng.random((size, size, size))

    def __call__(self, p: np.ndarray, freq: float) -> np.ndarray:  # [M, 3] -> [M] in [0, 1]
        q = p * freq
        i = np.floor(q)
        f = q - i
        f = f * f * (3 - 2 * f)
        i = i.astype(np.int64) % self.size
        j = (i + 1) % self.size
        n = self.size
        t = self.table.reshape(-1)
        x0, x1, y0, y1, z0, z1 = i[:, 0] * n * n, j[:, 0] * n * n, i[:, 1] * n, j[:, 1] * n, i[:, 2], j[:, 2]
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        lerp = lambda a, b, w: a + w * (b - a)  # noqa: E731
        c00 = lerp(t[x0 + y0 + z0], t[x0 + y0 + z1], fz)
        c01 = lerp(t[x0 + y1 + z0], t[x0 + y1 + z1], fz)
        c10 = lerp(t[x1 + y0 + z0], t[x1 + y0 + z1], fz)
        c11 = lerp(t[x1 + y1 + z0], t[x1 + y1 + z1], fz)
        return lerp(lerp(c00, c01, fy), lerp(c10, c11, fy), fx)

    def fbm(self, p: np.ndarray, freq: float, octaves: int = 3) -> np.ndarray:
        total, amp, norm = np.zeros(len(p)), 1.0, 0.0
        for k in range(octaves):
            total += amp * self(p, freq * 2**k)
            norm += amp
            amp *= 0.5
        return total / norm


def face_uv(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane coordinates of a point on an axis-aligned face: the two axes other than the normal's."""
    axis = np.argmax(np.abs(n), axis=1)
    a = np.where(axis == 0, p[:, 1], p[:, 0])
    b = np.where(axis == 2, p[:, 1], p[:, 2])
    return a, b


def _mix(c0, c1, t) -> np.ndarray:
    t = np.clip(np.asarray(t, dtype=np.float64), 0, 1)[:, None]
    return (1 - t) * np.asarray(c0, dtype=np.float64) + t * np.asarray(c1, dtype=np.float64)


def _rect(a, b, a0, a1, b0, b1) -> np.ndarray:
    return (a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)


def _frac(x):
    return x - np.floor(x)


def room(noise: ValueNoise, lo: np.ndarray, hi: np.ndarray):
    """Floor tiles, panelled ceiling, four walls (stripes; gradient + painting; plaster + door; window)."""
    center = (lo + hi) / 2

    def texture(p, n):
        w = p + center  # room-local -> world (the room is not rotated)
        x, y, z = w[:, 0], w[:, 1], w[:, 2]
        rgb = np.zeros_like(w)
        floor, ceil = n[:, 2] > 0.5, n[:, 2] < -0.5
        wx_lo, wx_hi = n[:, 0] > 0.5, n[:, 0] < -0.5
        wy_lo, wy_hi = n[:, 1] > 0.5, n[:, 1] < -0.5

        m = floor  # wooden tiles: two tones in a 0.5 m checker, grain along x, dark grout
        tile = (np.floor(x[m] / 0.5) + np.floor(y[m] / 0.5)) % 2
        grain = 0.85 + 0.15 * np.sin(x[m] * 45 + 6 * noise(w[m], 2.0))
        c = _mix((0.58, 0.40, 0.24), (0.40, 0.26, 0.15), tile) * grain[:, None]
        grout = (_frac(x[m] / 0.5) < 0.02) | (_frac(y[m] / 0.5) < 0.02)
        rgb[m] = np.where(grout[:, None], (0.2, 0.17, 0.15), c)

        m = ceil  # off-white panels with grey seams
        seam = (_frac(x[m] / 0.6) < 0.03) | (_frac(y[m] / 0.6) < 0.03)
        rgb[m] = np.where(seam[:, None], (0.62, 0.62, 0.6), (0.92, 0.91, 0.86))

        m = wx_lo  # blue vertical-stripe wallpaper
        stripe = _frac(y[m] / 0.2) < 0.5
        rgb[m] = np.where(stripe[:, None], (0.28, 0.42, 0.68), (0.78, 0.82, 0.9))

        m = wx_hi  # warm gradient with a framed noise painting
        c = _mix((0.9, 0.6, 0.32), (0.68, 0.22, 0.24), (y[m] - lo[1]) / (hi[1] - lo[1]))
        c *= (0.85 + 0.15 * z[m] / hi[2])[:, None]
        c[_rect(y[m], z[m], 0.3, 1.5, 1.0, 1.8)] = (0.15, 0.1, 0.05)
        inner = _rect(y[m], z[m], 0.36, 1.44, 1.06, 1.74)
        land = noise.fbm(w[m][inner], 3.0, 4)
        sky = (z[m][inner] - 1.06 + 0.25 * land > 0.35)[:, None]
        c[inner] = np.where(sky, _mix((0.3, 0.5, 0.85), (0.9, 0.95, 1.0), land),
                            _mix((0.15, 0.45, 0.15), (0.6, 0.7, 0.2), land))
        rgb[m] = c

        m = wy_lo  # green plaster with a panelled door
        c = _mix((0.42, 0.55, 0.38), (0.7, 0.8, 0.6), noise.fbm(w[m], 4.0, 3))
        door = _rect(x[m], z[m], -1.8, -0.9, 0.0, 2.0)
        panel = _rect(_frac((x[m] + 1.8) / 0.45) * 0.45, _frac(z[m] / 1.0), 0.06, 0.39, 0.08, 0.92)
        wood = np.where(panel[:, None], (0.5, 0.33, 0.2), (0.4, 0.26, 0.16))
        rgb[m] = np.where(door[:, None], wood, c)

        m = wy_hi  # beige with a window: sky gradient, white frame and mullions
        c = (0.86, 0.8, 0.68) * (0.92 + 0.08 * noise(w[m], 12.0))[:, None]
        win = _rect(x[m], z[m], -0.6, 1.0, 0.9, 2.0)
        glass = _rect(x[m], z[m], -0.55, 0.95, 0.95, 1.95) & (np.abs(x[m] - 0.2) > 0.03) & (np.abs(z[m] - 1.45) > 0.03)
        sky = _mix((0.45, 0.68, 0.95), (0.88, 0.93, 1.0), (2.0 - z[m]) / 1.1 + 0.3 * noise(w[m], 2.0))
        c = np.where(win[:, None], (0.97, 0.97, 0.97), c)
        rgb[m] = np.where(glass[:, None], sky, c)

        skirting = (z < 0.12) & ~(floor | ceil) & ~(wy_lo & (x >= -1.8) & (x <= -0.9))
        rgb[skirting] = (0.25, 0.2, 0.17)
        return rgb

    return texture


def wood(noise: ValueNoise):
    """Cabinet: noise-warped grain, darker drawer seams and handles on the sides."""

    def texture(p, n):
        grain = 0.5 + 0.5 * np.sin(p[:, 0] * 30 + 8 * noise(p, 3.0))
        c = _mix((0.62, 0.42, 0.26), (0.45, 0.28, 0.16), grain)
        side = np.abs(n[:, 2]) < 0.5
        seam = side & ((np.abs(p[:, 2] - 0.1) < 0.01) | (np.abs(p[:, 2] + 0.15) < 0.01))
        a, _ = face_uv(p, n)
        handle = side & (np.abs(a) < 0.08) & (np.abs(p[:, 2] - 0.22) < 0.02)
        c[seam] = (0.2, 0.13, 0.08)
        c[handle] = (0.85, 0.85, 0.8)
        return c

    return texture


def beach_ball():
    """Six coloured longitude sectors with white poles."""
    palette = np.array([(0.9, 0.15, 0.12), (0.98, 0.85, 0.15), (0.15, 0.35, 0.85),
                        (0.95, 0.95, 0.95), (0.15, 0.7, 0.3), (0.98, 0.5, 0.1)])

    def texture(p, n):
        sector = np.floor((np.arctan2(p[:, 1], p[:, 0]) + np.pi) / (2 * np.pi) * 6).astype(np.int64) % 6
        c = palette[sector]
        c[np.abs(n[:, 2]) > 0.92] = (0.97, 0.97, 0.97)
        return c

    return texture


def bands():
    """Column: red and white rings 0.15 m tall, grey caps."""

    def texture(p, n):
        ring = _frac(p[:, 2] / 0.3) < 0.5
        c = np.where(ring[:, None], (0.8, 0.15, 0.1), (0.95, 0.93, 0.88))
        c[np.abs(n[:, 2]) > 0.5] = (0.5, 0.5, 0.52)
        return c

    return texture


def crate(noise: ValueNoise):
    """Crate: orange and purple 9 cm checker with a little noise."""

    def texture(p, n):
        a, b = face_uv(p, n)
        check = (np.floor(a / 0.09) + np.floor(b / 0.09)) % 2
        return _mix((0.95, 0.6, 0.1), (0.35, 0.15, 0.45), check) * (0.9 + 0.1 * noise(p, 20.0))[:, None]

    return texture


def bookshelf(rng: np.random.Generator):
    """Bookshelf: dark frame; on its front four shelves of books with random colours, widths and heights."""
    palette = rng.uniform(0.1, 0.9, (97, 3))
    heights = rng.uniform(0.22, 0.38, 97)

    def texture(p, n):
        c = np.tile(np.array([0.3, 0.2, 0.12]), (len(p), 1))
        front = n[:, 0] < -0.5
        shelf = np.floor((p[:, 2] + 0.9) / 0.45).astype(np.int64)
        dz = (p[:, 2] + 0.9) - shelf * 0.45
        book = np.floor((p[:, 1] + 0.6) / 0.055 + 0.37 * shelf).astype(np.int64)
        key = (book * 7 + shelf * 31) % 97
        is_book = front & (dz > 0.03) & (dz < heights[key]) & (np.abs(p[:, 1]) < 0.56)
        c[is_book] = palette[key[is_book]]
        c[front & ~is_book & (dz > 0.03) & (np.abs(p[:, 1]) < 0.56)] = (0.12, 0.08, 0.05)
        return c

    return texture
