#!/usr/bin/env python3
"""Writes scenes/skinned.gltf: a capped tube on two joints (linear blend skinning) that
bends and turns over one second, over a ground of two placements of one quad (so the
scene is traced in two levels), with a camera. Run from the
repository root: python3 scenes/skinned.py"""
import base64, json, math, struct

R, S, RADIUS, HEIGHT = 12, 16, 0.25, 2.0
pos, joints, weights, idx = [], [], [], []
for r in range(R + 1):
    y = HEIGHT * r / R
    w_mid = min(max((y - 0.6) / 0.8, 0.0), 1.0)
    for s in range(S):
        a = 2 * math.pi * s / S
        pos.append((RADIUS * math.cos(a), y, RADIUS * math.sin(a)))
        joints.append((0, 1, 0, 0))
        weights.append((1.0 - w_mid, w_mid, 0.0, 0.0))
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
    for s in range(S):
        a, b = ring * S + s, ring * S + (s + 1) % S
        idx += [centre, a, b] if flip else [centre, b, a]
ground = [(-1.0, -0.01, -2.0), (1.0, -0.01, -2.0), (1.0, -0.01, 2.0), (-1.0, -0.01, 2.0)]
ground_idx = [0, 2, 1, 0, 3, 2]

def rot(axis, deg):
    h = math.radians(deg) / 2
    s = math.sin(h)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(h))

times = [0.0, 0.5, 1.0]
mid_rot = [rot((0, 0, 1), d) for d in (0.0, 35.0, 70.0)]
root_rot = [rot((0, 1, 0), d) for d in (0.0, 45.0, 90.0)]
ibm_root = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
ibm_mid = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, -1, 0, 1]

blob = bytearray()
views, accessors = [], []

def add(data, fmt, count, type_, ctype, target=None, minmax=None):
    while len(blob) % 4:
        blob.append(0)
    off = len(blob)
    blob.extend(struct.pack("<" + fmt * (len(data)), *data))
    view = {"buffer": 0, "byteOffset": off, "byteLength": len(blob) - off}
    if target:
        view["target"] = target
    views.append(view)
    acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": count, "type": type_}
    if minmax:
        acc["min"], acc["max"] = minmax
    accessors.append(acc)
    return len(accessors) - 1

def bounds(points):
    return [[min(p[i] for p in points) for i in range(3)], [max(p[i] for p in points) for i in range(3)]]

flat = lambda rows: [x for row in rows for x in row]
a_pos = add(flat(pos), "f", len(pos), "VEC3", 5126, 34962, bounds(pos))
a_joints = add(flat(joints), "B", len(joints), "VEC4", 5121, 34962)
a_weights = add(flat(weights), "f", len(weights), "VEC4", 5126, 34962)
a_idx = add(idx, "H", len(idx), "SCALAR", 5123, 34963)
a_gpos = add(flat(ground), "f", 4, "VEC3", 5126, 34962, bounds(ground))
a_gidx = add(ground_idx, "H", 6, "SCALAR", 5123, 34963)
a_ibm = add(ibm_root + ibm_mid, "f", 2, "MAT4", 5126)
a_time = add(times, "f", 3, "SCALAR", 5126, None, [[0.0], [1.0]])
a_mid = add(flat(mid_rot), "f", 3, "VEC4", 5126)
a_root = add(flat(root_rot), "f", 3, "VEC4", 5126)

gltf = {
    "asset": {"version": "2.0", "generator": "bvhtrace scenes/skinned.py"},
    "scene": 0,
    "scenes": [{"nodes": [0, 1, 3, 4, 5]}],
    "nodes": [
        {"name": "tube", "mesh": 0, "skin": 0},
        {"name": "root joint", "children": [2]},
        {"name": "mid joint", "translation": [0.0, 1.0, 0.0]},
        {"name": "camera", "camera": 0, "translation": [0.0, 1.2, 5.0]},
        {"name": "ground left", "mesh": 1, "translation": [-1.0, 0.0, 0.0]},
        {"name": "ground right", "mesh": 1, "translation": [1.0, 0.0, 0.0]},
    ],
    "meshes": [
        {"name": "tube", "primitives": [{"attributes": {"POSITION": a_pos, "JOINTS_0": a_joints, "WEIGHTS_0": a_weights}, "indices": a_idx}]},
        {"name": "ground", "primitives": [{"attributes": {"POSITION": a_gpos}, "indices": a_gidx}]},
    ],
    "skins": [{"joints": [1, 2], "inverseBindMatrices": a_ibm}],
    "cameras": [{"type": "perspective", "perspective": {"yfov": 0.6, "znear": 0.05, "aspectRatio": 1.3333}}],
    "animations": [{
        "name": "bend",
        "samplers": [{"input": a_time, "output": a_mid, "interpolation": "LINEAR"},
                     {"input": a_time, "output": a_root, "interpolation": "LINEAR"}],
        "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}},
                     {"sampler": 1, "target": {"node": 1, "path": "rotation"}}],
    }],
    "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()}],
    "bufferViews": views,
    "accessors": accessors,
}
with open("scenes/skinned.gltf", "w") as f:
    json.dump(gltf, f, indent=1)
    f.write("\n")
print(f"scenes/skinned.gltf: {len(idx) // 3} + 2 x 2 triangles, {len(pos)} skinned vertices")
