"""Writes scenes/sky.hdr: a procedural equirectangular sky for the path tracer's
environment map (`render --shade path --environment scenes/sky.hdr`).

256 x 128 Radiance RGBE, run-length encoded: a sky from pale blue at the horizon to deep
blue overhead, a brown ground below, and a sun 2.5 degrees wide toward (0.45, 0.55, -0.70)
of radiance about 400. The convention is `bvhtrace_path::environment`'s: +Y up, the
image's centre column toward -Z, row 0 straight up.

    python3 scenes/sky.py   (from the repository root)
"""
import math

W, H = 256, 128
SUN = (0.45, 0.55, -0.70)


def rgbe(r, g, b):
    m = max(r, g, b)
    if m < 1e-32:
        return (0, 0, 0, 0)
    e = math.frexp(m)[1]
    s = 256.0 / 2.0**e
    return (int(r * s), int(g * s), int(b * s), e + 128)


def radiance(d, sun):
    y = d[1]
    if y >= 0:
        t = y**0.5
        c = [0.55 + (0.15 - 0.55) * t, 0.65 + (0.35 - 0.65) * t, 0.85 + (0.9 - 0.85) * t]
    else:
        c = [0.25, 0.2, 0.15]
    if sum(a * b for a, b in zip(d, sun)) > math.cos(math.radians(2.5)):
        c = [c[0] + 400, c[1] + 360, c[2] + 300]
    return c


def runs(values):
    """One channel of a scanline in the new run-length encoding."""
    out, i = bytearray(), 0
    while i < len(values):
        j = i
        while j < len(values) and j - i < 127 and values[j] == values[i]:
            j += 1
        if j - i >= 3:
            out += bytes([128 + j - i, values[i]])
            i = j
            continue
        j = i
        while j < len(values) and j - i < 128:
            if j + 2 < len(values) and values[j] == values[j + 1] == values[j + 2]:
                break
            j += 1
        out += bytes([j - i]) + bytes(values[i:j])
        i = j
    return out


def main():
    n = math.sqrt(sum(c * c for c in SUN))
    sun = tuple(c / n for c in SUN)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (H, W))
    for row in range(H):
        theta = (row + 0.5) / H * math.pi
        pixels = []
        for col in range(W):
            phi = ((col + 0.5) / W - 0.5) * 2 * math.pi
            d = (math.sin(theta) * math.sin(phi), math.cos(theta), -math.sin(theta) * math.cos(phi))
            pixels.append(rgbe(*radiance(d, sun)))
        out += bytes([2, 2, W >> 8, W & 255])
        for c in range(4):
            out += runs([p[c] for p in pixels])
    with open("scenes/sky.hdr", "wb") as f:
        f.write(out)


if __name__ == "__main__":
    main()
