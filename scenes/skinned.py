#!/usr/bin/env python3
"""Writes the deforming test scenes, from the repository root: python3 scenes/skinned.py

scenes/skinned.gltf: a capped tube on two joints (linear blend skinning) that bends and
turns over one second, over a ground of two placements of one quad (so the scene is traced
in two levels), with a camera.

scenes/morph.gltf: the same, with morph targets: the tube swells in its middle (one
target, STEP weights, morphed before it is skinned), and a sphere beside it, placed by its
node, stretches and bulges (two targets, LINEAR weights)."""
import base64, json, math, struct

R, S, RADIUS, HEIGHT = 12, 16, 0.25, 2.0


def tube():
    """The capped tube: positions, joints, weights, indices, swell deltas."""
    pos, joints, weights, idx, swell = [], [], [], [], []
    for r in range(R + 1):
        y = HEIGHT * r / R
        w_mid = min(max((y - 0.6) / 0.8, 0.0), 1.0)
        bump = 0.12 * math.sin(math.pi * r / R)
        for s in range(S):
            a = 2 * math.pi * s / S
            pos.append((RADIUS * math.cos(a), y, RADIUS * math.sin(a)))
            joints.append((0, 1, 0, 0))
            weights.append((1.0 - w_mid, w_mid, 0.0, 0.0))
            swell.append((bump * math.cos(a), 0.0, bump * math.sin(a)))
    for r in range(R):
        for s in range(S):
            a, b = r * S + s, r * S + (s + 1) % S
            c, d = a + S, b + S
            idx += [a, c, b, b, c, d]
    # Caps: a centre vertex at each end.
    for y, ring, w_mid, flip in ((0.0, 0, 0.0, True), (HEIGHT, R, 1.0, False)):
        centre = len(pos)
        pos.append((0.0, y, 0.0))
        joints.append((0, 1, 0, 0))
        weights.append((1.0 - w_mid, w_mid, 0.0, 0.0))
        swell.append((0.0, 0.0, 0.0))
        for s in range(S):
            a, b = ring * S + s, ring * S + (s + 1) % S
            idx += [centre, a, b] if flip else [centre, b, a]
    return pos, joints, weights, idx, swell


def sphere(rings=8, segs=12, radius=0.35):
    """A UV sphere and two targets: stretched along +Y, bulged along +X."""
    pos, stretch, bulge, idx = [], [], [], []
    for r in range(rings + 1):
        th = math.pi * r / rings
        for s in range(segs + 1):
            ph = 2 * math.pi * s / segs
            p = (radius * math.sin(th) * math.cos(ph), radius * math.cos(th), radius * math.sin(th) * math.sin(ph))
            pos.append(p)
            stretch.append((0.0, 0.8 * p[1], 0.0))
            bulge.append((max(p[0], 0.0) * 1.2, 0.0, 0.0))
    for r in range(rings):
        for s in range(segs):
            a = r * (segs + 1) + s
            b, c, d = a + 1, a + segs + 1, a + segs + 2
            idx += [a, b, c, b, d, c]
    return pos, stretch, bulge, idx


def rot(axis, deg):
    h = math.radians(deg) / 2
    s = math.sin(h)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(h))


class Blob:
    """The embedded buffer, its views and accessors."""

    def __init__(self):
        self.data, self.views, self.accessors = bytearray(), [], []

    def add(self, data, fmt, count, type_, ctype, target=None, minmax=None):
        while len(self.data) % 4:
            self.data.append(0)
        off = len(self.data)
        self.data.extend(struct.pack("<" + fmt * (len(data)), *data))
        view = {"buffer": 0, "byteOffset": off, "byteLength": len(self.data) - off}
        if target:
            view["target"] = target
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": ctype, "count": count, "type": type_}
        if minmax:
            acc["min"], acc["max"] = minmax
        self.accessors.append(acc)
        return len(self.accessors) - 1


def bounds(points):
    return [[min(p[i] for p in points) for i in range(3)], [max(p[i] for p in points) for i in range(3)]]


flat = lambda rows: [x for row in rows for x in row]


def scene(morph):
    """The skinned scene; with `morph`, the tube's swell target and the sphere too."""
    pos, joints, weights, idx, swell = tube()
    ground = [(-1.0, -0.01, -2.0), (1.0, -0.01, -2.0), (1.0, -0.01, 2.0), (-1.0, -0.01, 2.0)]
    times = [0.0, 0.5, 1.0]
    b = Blob()
    f, vec3, vec4 = 5126, "VEC3", "VEC4"
    a_pos = b.add(flat(pos), "f", len(pos), vec3, f, 34962, bounds(pos))
    a_joints = b.add(flat(joints), "B", len(joints), vec4, 5121, 34962)
    a_weights = b.add(flat(weights), "f", len(weights), vec4, f, 34962)
    a_idx = b.add(idx, "H", len(idx), "SCALAR", 5123, 34963)
    a_gpos = b.add(flat(ground), "f", 4, vec3, f, 34962, bounds(ground))
    a_gidx = b.add([0, 2, 1, 0, 3, 2], "H", 6, "SCALAR", 5123, 34963)
    ibm = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1] + [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, -1, 0, 1]
    a_ibm = b.add(ibm, "f", 2, "MAT4", f)
    a_time = b.add(times, "f", 3, "SCALAR", f, None, [[0.0], [1.0]])
    a_mid = b.add(flat(rot((0, 0, 1), d) for d in (0.0, 35.0, 70.0)), "f", 3, vec4, f)
    a_root = b.add(flat(rot((0, 1, 0), d) for d in (0.0, 45.0, 90.0)), "f", 3, vec4, f)
    tube_prim = {"attributes": {"POSITION": a_pos, "JOINTS_0": a_joints, "WEIGHTS_0": a_weights}, "indices": a_idx}
    samplers = [{"input": a_time, "output": a_mid, "interpolation": "LINEAR"},
                {"input": a_time, "output": a_root, "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 2, "path": "rotation"}},
                {"sampler": 1, "target": {"node": 1, "path": "rotation"}}]
    nodes = [
        {"name": "tube", "mesh": 0, "skin": 0},
        {"name": "root joint", "children": [2]},
        {"name": "mid joint", "translation": [0.0, 1.0, 0.0]},
        {"name": "camera", "camera": 0, "translation": [0.0, 1.2, 5.0]},
        {"name": "ground left", "mesh": 1, "translation": [-1.0, 0.0, 0.0]},
        {"name": "ground right", "mesh": 1, "translation": [1.0, 0.0, 0.0]},
    ]
    meshes = [
        {"name": "tube", "primitives": [tube_prim]},
        {"name": "ground", "primitives": [{"attributes": {"POSITION": a_gpos}, "indices": a_gidx}]},
    ]
    if morph:
        tube_prim["targets"] = [{"POSITION": b.add(flat(swell), "f", len(swell), vec3, f, None, bounds(swell))}]
        meshes[0]["weights"] = [0.5]
        a_step = b.add([0.0, 0.5], "f", 2, "SCALAR", f, None, [[0.0], [0.5]])
        samplers.append({"input": a_step, "output": b.add([0.0, 1.0], "f", 2, "SCALAR", f), "interpolation": "STEP"})
        channels.append({"sampler": 2, "target": {"node": 0, "path": "weights"}})
        spos, stretch, bulge, sidx = sphere()
        targets = [{"POSITION": b.add(flat(d), "f", len(d), vec3, f, None, bounds(d))} for d in (stretch, bulge)]
        sprim = {"attributes": {"POSITION": b.add(flat(spos), "f", len(spos), vec3, f, 34962, bounds(spos))},
                 "indices": b.add(sidx, "H", len(sidx), "SCALAR", 5123, 34963), "targets": targets}
        meshes.append({"name": "sphere", "primitives": [sprim]})
        nodes.append({"name": "sphere", "mesh": 2, "translation": [-0.9, 0.6, 0.3], "weights": [0.0, 0.0]})
        a_sw = b.add([0.0, 0.0, 1.0, 0.0, 0.5, 1.0], "f", 6, "SCALAR", f)
        samplers.append({"input": a_time, "output": a_sw, "interpolation": "LINEAR"})
        channels.append({"sampler": 3, "target": {"node": 6, "path": "weights"}})
    return {
        "asset": {"version": "2.0", "generator": "bvhtrace scenes/skinned.py"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 3, 4, 5] + ([6] if morph else [])}],
        "nodes": nodes,
        "meshes": meshes,
        "skins": [{"joints": [1, 2], "inverseBindMatrices": a_ibm}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.6, "znear": 0.05, "aspectRatio": 1.3333}}],
        "animations": [{"name": "bend", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": len(b.data), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(b.data)).decode()}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }


for name, morph in (("skinned", False), ("morph", True)):
    g = scene(morph)
    with open(f"scenes/{name}.gltf", "w") as out:
        json.dump(g, out, indent=1)
        out.write("\n")
    tris = sum(g["accessors"][p["indices"]]["count"] // 3 for m in g["meshes"] for p in m["primitives"])
    print(f"scenes/{name}.gltf: {len(g['meshes'])} meshes, {tris} triangles before instancing")
