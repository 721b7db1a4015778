#!/usr/bin/env python3
"""Writes scenes/foliage.gltf, from the repository root: python3 scenes/foliage.py

An alpha-tested test scene (glTF alphaMode MASK): a trunk carrying a crown of leaf cards
(quads cut by a procedural leaf-shaped texture), the crown placed twice, the second time
mirrored; a fence whose texture coordinates run past 0..1 (REPEAT along it, a grille cut by
its texture) and a gate cut by the same texture under MIRRORED_REPEAT and CLAMP_TO_EDGE; a
ground; a camera. The textures are PNGs made here (no third-party data), embedded."""
import base64, json, math, struct, zlib


def png(width, height, rgba):
    """An 8-bit RGBA PNG of `rgba` (rows from the top, 4 bytes per texel)."""
    raw = b"".join(b"\x00" + bytes(rgba[y * width * 4:(y + 1) * width * 4]) for y in range(height))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xffffffff)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def leaf_texture(n=64):
    """A pointed leaf along v, with a cut-out midrib: alpha 255 inside, 0 outside."""
    out = []
    for y in range(n):
        for x in range(n):
            u, v = (x + 0.5) / n * 2 - 1, (y + 0.5) / n
            half_width = 0.9 * math.sin(math.pi * v) ** 0.8 * (1 - 0.35 * v)
            inside = abs(u) < half_width and abs(u) > 0.04
            out += [60, 140, 50, 255 if inside else 0]
    return png(n, n, out)


def grille_texture(n=32):
    """Bars 6 texels wide every 16: a square grille."""
    out = []
    for y in range(n):
        for x in range(n):
            bar = x % 16 < 6 or y % 16 < 6
            out += [150, 120, 90, 255 if bar else 0]
    return png(n, n, out)


class Blob:
    def __init__(self):
        self.data, self.views, self.accessors = bytearray(), [], []

    def view(self, raw, target=None):
        while len(self.data) % 4:
            self.data.append(0)
        v = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target:
            v["target"] = target
        self.data.extend(raw)
        self.views.append(v)
        return len(self.views) - 1

    def add(self, values, fmt, count, type_, ctype, target=None, minmax=False):
        acc = {"bufferView": self.view(struct.pack("<" + fmt * len(values), *values), target),
               "componentType": ctype, "count": count, "type": type_}
        if minmax:
            k = len(values) // count
            acc["min"] = [min(values[i::k]) for i in range(k)]
            acc["max"] = [max(values[i::k]) for i in range(k)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


b = Blob()
F, ARRAY, ELEMENT = 5126, 34962, 34963


def grid_quad(corners, uvs, nu, nv, out):
    """Appends a quad (corners counter-clockwise, with texture coordinates) cut into
    nu x nv cells of two triangles each to `out` = (positions, uvs, indices): small
    triangles, so that most fall wholly inside or outside a mask's cut."""
    pos, tex, idx = out
    lerp = lambda a, b, t: tuple(a[i] + (b[i] - a[i]) * t for i in range(len(a)))
    base = len(pos)
    for j in range(nv + 1):
        for i in range(nu + 1):
            s, t = i / nu, j / nv
            pos.append(lerp(lerp(corners[0], corners[1], s), lerp(corners[3], corners[2], s), t))
            tex.append(lerp(lerp(uvs[0], uvs[1], s), lerp(uvs[3], uvs[2], s), t))
    for j in range(nv):
        for i in range(nu):
            a = base + j * (nu + 1) + i
            idx += [a, a + 1, a + nu + 2, a, a + nu + 2, a + nu + 1]


def mesh_of(name, out, material):
    pos, tex, idx = out
    p = b.add([c for q in pos for c in q], "f", len(pos), "VEC3", F, ARRAY, True)
    t = b.add([c for q in tex for c in q], "f", len(tex), "VEC2", F, ARRAY)
    i = b.add(idx, "H", len(idx), "SCALAR", 5123, ELEMENT)
    prim = {"attributes": {"POSITION": p, "TEXCOORD_0": t}, "indices": i, "material": material}
    return {"name": name, "primitives": [prim]}


def quad_mesh(name, corners, uvs, material, nu=1, nv=1):
    """A quad (corners counter-clockwise) with texture coordinates, in nu x nv cells."""
    out = ([], [], [])
    grid_quad(corners, uvs, nu, nv, out)
    return mesh_of(name, out, material)


def box_mesh(name, lo, hi, material):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    p = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    faces = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3)]
    idx = [i for a, b_, c, d in faces for i in (a, b_, c, a, c, d)]
    pos = b.add([c for q in p for c in q], "f", 8, "VEC3", F, ARRAY, True)
    ind = b.add(idx, "H", len(idx), "SCALAR", 5123, ELEMENT)
    return {"name": name, "primitives": [{"attributes": {"POSITION": pos}, "indices": ind, "material": material}]}


def leaf_cards():
    """Twelve leaf cards around a crown, tilted, each the whole leaf texture in 4 x 6 cells."""
    out = ([], [], [])
    for k in range(12):
        a = 2 * math.pi * k / 12 + 0.3 * (k % 3)
        r, y = 0.35 + 0.12 * (k % 4), 1.7 + 0.18 * (k % 5)
        c, s = math.cos(a), math.sin(a)
        # A 0.5 x 0.8 card pointing outward and up.
        base = (r * c, y, r * s)
        reach = (0.64 * c, 0.44, 0.64 * s)
        side = (-s * 0.25, 0.0, c * 0.25)
        quad = [
            tuple(base[i] - side[i] for i in range(3)),
            tuple(base[i] + side[i] for i in range(3)),
            tuple(base[i] + side[i] + reach[i] for i in range(3)),
            tuple(base[i] - side[i] + reach[i] for i in range(3)),
        ]
        grid_quad(quad, [(0, 0), (1, 0), (1, 1), (0, 1)], 4, 6, out)
    return mesh_of("crown", out, 0)


def camera_rotation(pitch, yaw):
    """The quaternion of a camera turned `yaw` degrees about +Y, then pitched `pitch`."""
    p, y = math.radians(pitch) / 2, math.radians(yaw) / 2
    qp = (math.sin(p), 0.0, 0.0, math.cos(p))
    qy = (0.0, math.sin(y), 0.0, math.cos(y))
    x1, y1, z1, w1 = qy
    x2, y2, z2, w2 = qp
    return [w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]


images = [leaf_texture(), grille_texture()]
image_json = [{"name": name, "mimeType": "image/png", "bufferView": b.view(data)}
              for name, data in zip(("leaf", "grille"), images)]

meshes = [
    leaf_cards(),
    box_mesh("trunk", (-0.08, 0.0, -0.08), (0.08, 1.9, 0.08), 3),
    # The fence: 6 long, 1 high, its texture repeated 6 times along it (u runs 0..6).
    quad_mesh("fence", [(-3, 0, -1.2), (3, 0, -1.2), (3, 1, -1.2), (-3, 1, -1.2)], [(0, 1), (6, 1), (6, 0), (0, 0)], 1, 48, 8),
    # The gate: its coordinates run -1..2, mirrored across and clamped up.
    quad_mesh("gate", [(1.6, 0, 0.6), (2.6, 0, 1.0), (2.6, 1.2, 1.0), (1.6, 1.2, 0.6)], [(-1, 1.5), (2, 1.5), (2, -0.5), (-1, -0.5)], 2, 12, 8),
    quad_mesh("ground", [(-4, 0, -4), (-4, 0, 4), (4, 0, 4), (4, 0, -4)], [(0, 0)] * 4, 4),
]
materials = [
    {"name": "leaves", "alphaMode": "MASK", "alphaCutoff": 0.5, "doubleSided": True,
     "pbrMetallicRoughness": {"baseColorFactor": [0.35, 0.7, 0.3, 1], "baseColorTexture": {"index": 0}}},
    {"name": "fence", "alphaMode": "MASK", "doubleSided": True,
     "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.45, 0.3, 1], "baseColorTexture": {"index": 1}}},
    {"name": "gate", "alphaMode": "MASK", "doubleSided": True,
     "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.55, 1], "baseColorTexture": {"index": 2}}},
    {"name": "bark", "pbrMetallicRoughness": {"baseColorFactor": [0.4, 0.28, 0.18, 1]}},
    {"name": "ground", "pbrMetallicRoughness": {"baseColorFactor": [0.75, 0.72, 0.65, 1]}},
]
gltf = {
    "asset": {"version": "2.0", "generator": "bvhtrace scenes/foliage.py"},
    "scene": 0,
    "scenes": [{"nodes": [0, 1, 2, 3, 4, 5, 6, 7]}],
    "nodes": [
        {"name": "crown", "mesh": 0, "translation": [-1.0, 0, 0]},
        {"name": "trunk", "mesh": 1, "translation": [-1.0, 0, 0]},
        # The same crown and trunk again, mirrored (scale x -1): its cards keep their cut.
        {"name": "crown mirrored", "mesh": 0, "translation": [0.8, 0, -0.2], "scale": [-1, 1, 1]},
        {"name": "trunk mirrored", "mesh": 1, "translation": [0.8, 0, -0.2], "scale": [-1, 1, 1]},
        {"name": "fence", "mesh": 2},
        {"name": "gate", "mesh": 3},
        {"name": "ground", "mesh": 4},
        # Above and in front, looking down at the crowns and the ground behind them.
        {"name": "camera", "camera": 0, "translation": [0.3, 4.0, 5.2], "rotation": camera_rotation(-30.0, 3.0)},
    ],
    "meshes": meshes,
    "materials": materials,
    "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 0}, {"source": 1, "sampler": 1}],
    "samplers": [{"wrapS": 10497, "wrapT": 10497}, {"wrapS": 33648, "wrapT": 33071}],
    "images": image_json,
    "cameras": [{"type": "perspective", "perspective": {"yfov": 0.9, "znear": 0.05, "aspectRatio": 1.3333}}],
    "buffers": [{"byteLength": len(b.data), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(b.data)).decode()}],
    "bufferViews": b.views,
    "accessors": b.accessors,
}
with open("scenes/foliage.gltf", "w") as f:
    json.dump(gltf, f, indent=1)
    f.write("\n")
print(f"scenes/foliage.gltf: {sum(len(m['primitives']) for m in meshes)} primitives, {len(b.data)} bytes of buffer")
