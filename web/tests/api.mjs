// The npm package's API in Node, as a user calls it: every promise the README makes,
// asserted. Exits non-zero on the first failure.
//
// usage: node web/tests/api.mjs PKG_DIR [SCENE.gltf]
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";

const [pkg, gltf] = process.argv.slice(2);
const { default: init, Bvh, InstancedBvh } = await import(path.resolve(pkg, "bvhtrace_web.js"));
await init({ module_or_path: fs.readFileSync(path.resolve(pkg, "bvhtrace_web_bg.wasm")) });

const MISS = 0xffffffff;
let checks = 0;
const check = (name, f) => {
  f();
  checks++;
  console.log(`ok: ${name}`);
};

// A unit quad at z = 0 (two triangles sharing the diagonal), and a unit quad at z = -1.
const quad = (z) => [0, 0, z, 1, 0, z, 1, 1, z, 0, 1, z];
const positions = new Float32Array([...quad(0), ...quad(-1)]);
const indices = new Uint32Array([0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7]);
const bvh = new Bvh(positions, indices);

check("counts and bounds", () => {
  assert.equal(bvh.triangleCount, 4);
  assert.ok(bvh.nodeCount >= 1);
  assert.deepEqual(Array.from(bvh.bounds()), [0, 0, -1, 1, 1, 0]);
  assert.equal(bvh.backend, "wasm-simd128");
});

check("raycastFirst: the nearest triangle, its barycentrics and point; undefined on a miss", () => {
  const h = bvh.raycastFirst(0.75, 0.25, 5, 0, 0, -1);
  assert.equal(h.t, 5);
  assert.equal(h.primitive, 0);
  assert.deepEqual(h.point.map((x) => Math.round(x * 1e6) / 1e6), [0.75, 0.25, 0]);
  assert.ok(Math.abs(1 - h.u - h.v - 0.25) < 1e-6);
  assert.equal(bvh.raycastFirst(2, 2, 5, 0, 0, -1), undefined);
  // Past the first quad's distance: the second quad.
  assert.equal(bvh.raycastFirst(0.25, 0.75, 5, 0, 0, -1, 5.5).primitive, 3);
  // Within [0, 5): nothing.
  assert.equal(bvh.raycastFirst(0.25, 0.75, 5, 0, 0, -1, 0, 5), undefined);
});

check("watertight: a ray down the shared diagonal hits exactly one of its triangles", () => {
  const h = bvh.raycastFirst(0.5, 0.5, 5, 0, 0, -1);
  assert.ok(h && (h.primitive === 0 || h.primitive === 1) && h.t === 5);
});

check("intersect: a batch's typed arrays agree with raycastFirst ray by ray", () => {
  const starts = [[0.75, 0.25], [0.25, 0.75], [0.5, 0.5], [2, 2], [0.1, 0.9]];
  const origins = new Float32Array(starts.flatMap(([x, y]) => [x, y, 5]));
  const dirs = new Float32Array(starts.flatMap(() => [0, 0, -1]));
  const hits = bvh.intersect(origins, dirs);
  assert.equal(hits.count, 5);
  assert.equal(hits.hitCount, 4);
  assert.ok(hits.t instanceof Float32Array && hits.primitive instanceof Uint32Array);
  starts.forEach(([x, y], i) => {
    const one = bvh.raycastFirst(x, y, 5, 0, 0, -1);
    assert.equal(hits.primitive[i], one ? one.primitive : MISS);
    if (one) assert.deepEqual([hits.t[i], hits.u[i], hits.v[i]], [one.t, Math.fround(one.u), Math.fround(one.v)]);
  });
  assert.equal(hits.t[3], Infinity);
});

check("any hit and occluded: the verdict, within far", () => {
  const o = new Float32Array([0.3, 0.3, 5, 0.3, 0.3, 5, 3, 3, 5]);
  const d = new Float32Array([0, 0, -1, 0, 0, 1, 0, 0, -1]);
  const any = bvh.intersect(o, d, { anyHit: true });
  assert.deepEqual(Array.from(any.primitive).map((p) => p !== MISS), [true, false, false]);
  const short = bvh.intersect(o, d, { anyHit: true, far: 4 });
  assert.equal(short.hitCount, 0);
  assert.equal(bvh.occluded(0.3, 0.3, 5, 0, 0, -1), true);
  assert.equal(bvh.occluded(0.3, 0.3, 5, 0, 0, -1, 0, 4.5), false);
});

check("refit: the vertices moved, the hits follow", () => {
  const moved = positions.map((x, i) => (i % 3 === 2 ? x + 2 : x));
  const b = new Bvh(positions, indices);
  b.refit(moved);
  assert.equal(b.raycastFirst(0.75, 0.25, 5, 0, 0, -1).t, 3);
  assert.throws(() => b.refit(new Float32Array(9)), /index|vertices|triangles/);
  // A failed refit leaves the tree as it was.
  assert.equal(b.raycastFirst(0.75, 0.25, 5, 0, 0, -1).t, 3);
  b.free();
});

check("bad input: an Error naming the item and the cause", () => {
  const bad = (f, re) => assert.throws(f, (e) => e instanceof Error && re.test(e.message));
  bad(() => new Bvh(new Float32Array([0, 0, 0, 1, 0, 0, 0, NaN, 0])), /triangle 0: corner 2 has a non-finite/);
  bad(() => new Bvh(new Float32Array(9), new Uint32Array([0, 1, 7])), /triangle 0: vertex index 7 is out of range/);
  bad(() => new Bvh(new Float32Array(10)), /not a whole number of vertices/);
  bad(() => new Bvh(new Float32Array(12)), /not a whole number of triangles/);
  bad(() => new Bvh(new Float32Array(9), new Uint32Array([0, 1])), /indices: 2 is not a whole number/);
  bad(() => bvh.intersect(new Float32Array(3), new Float32Array(6)), /three per ray/);
  bad(() => bvh.intersect(new Float32Array(3), new Float32Array(3), { far: "x" }), /options.far must be a number/);
  bad(() => Bvh.fromGltf(new Uint8Array([1, 2, 3]), "broken.glb"), /broken.glb/);
});

check("toBytes and fromBytes: the same tree, the same hits; other bytes an Error", () => {
  const copy = Bvh.fromBytes(bvh.toBytes());
  assert.equal(copy.nodeCount, bvh.nodeCount);
  assert.deepEqual(copy.raycastFirst(0.3, 0.6, 5, 0, 0, -1), bvh.raycastFirst(0.3, 0.6, 5, 0, 0, -1));
  copy.free();
  const bytes = bvh.toBytes();
  assert.throws(() => Bvh.fromBytes(bytes.slice(0, 30)), /Bvh.fromBytes: .* bytes for/);
  assert.throws(() => Bvh.fromBytes(new Uint8Array(40)), /not a bvhtrace tree/);
  // A child link pointing past the nodes: refused by the checks, not walked.
  const broken = bytes.slice();
  new DataView(broken.buffer).setUint32(20 + 12, 1000, true);
  assert.throws(() => Bvh.fromBytes(broken), /Bvh.fromBytes: node 0: bad children 1, 1000/);
  const shallow = bytes.slice();
  new DataView(shallow.buffer).setUint32(8, 0, true);
  assert.throws(() => Bvh.fromBytes(shallow), /Bvh.fromBytes: depth 0 stated/);
});

check("instances: one mesh placed twice, moved, each hit naming its instance", () => {
  const scene = new InstancedBvh();
  const mesh = scene.addMesh(bvh);
  // Column-major 4x4 matrices (three.js Matrix4.elements): a translation by (x, 0, 0).
  const shift = (x) => new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, x, 0, 0, 1]);
  assert.equal(scene.addInstance(mesh, shift(0)), 0);
  assert.equal(scene.addInstance(mesh, shift(5)), 1);
  const o = new Float32Array([0.75, 0.25, 5, 5.75, 0.25, 5, 3, 0.5, 5]);
  const d = new Float32Array([0, 0, -1, 0, 0, -1, 0, 0, -1]);
  const h = scene.intersect(o, d);
  assert.deepEqual(Array.from(h.instance), [0, 1, MISS]);
  assert.deepEqual(Array.from(h.meshPrimitive), [0, 0, MISS]);
  assert.deepEqual(Array.from(h.t), [5, 5, Infinity]);
  assert.equal(h.primitive[1], 4 + h.primitive[0], "primitive numbers the instances' triangles in turn");
  const one = scene.raycastFirst(5.75, 0.25, 5, 0, 0, -1);
  assert.equal(one.instance, 1);
  assert.deepEqual(one.point.map((x) => Math.round(x * 1e6) / 1e6), [5.75, 0.25, 0]);
  // Moved: the second instance to x = 2.5, lifted by 1.
  const lifted = shift(2.5);
  lifted[14] = 1;
  scene.setTransforms(new Float32Array([...shift(0), ...lifted]));
  assert.equal(scene.raycastFirst(3, 0.5, 5, 0, 0, -1).t, 4);
  assert.equal(scene.raycastFirst(5.75, 0.25, 5, 0, 0, -1), undefined);
  assert.throws(() => scene.addInstance(3, shift(0)), /instance 2: mesh 3 was not added/);
  const projective = shift(0);
  projective[3] = 0.5;
  assert.throws(() => scene.addInstance(mesh, projective), /instance 2: the transform's last row/);
  const flat = shift(0);
  flat[0] = 0;
  assert.throws(() => scene.setTransforms(new Float32Array([...flat, ...shift(1)])), /instance 0/);
  assert.equal(scene.raycastFirst(3, 0.5, 5, 0, 0, -1).t, 4, "a refused move moves nothing");
  scene.free();
});

// The automatic choice: Node has no WebGPU, so the WebAssembly walk, saying why; asking
// for WebGPU there is an error, and an unknown backend too.
const auto = await Bvh.create(positions, indices);
check("create: the WebAssembly walk in Node, with the reason", () => {
  assert.equal(auto.backend, "wasm-simd128");
  assert.match(auto.backendNote, /no WebGPU/);
});
const asyncHits = await auto.intersectAsync(new Float32Array([0.75, 0.25, 5]), new Float32Array([0, 0, -1]));
check("intersectAsync on the WebAssembly walk", () => assert.equal(asyncHits.primitive[0], 0));
await assert.rejects(Bvh.create(positions, indices, { backend: "webgpu" }), /no WebGPU/);
await assert.rejects(Bvh.create(positions, indices, { backend: "cuda" }), /"auto", "webgpu" or "wasm"/);
checks += 2;
auto.free();

if (gltf) {
  // A glTF scene built directly: the same hits as the same triangles given as positions.
  const scene = Bvh.fromGltf(fs.readFileSync(gltf), path.basename(gltf));
  check(`fromGltf (${path.basename(gltf)}): ${scene.triangleCount} triangles`, () => {
    assert.ok(scene.triangleCount > 0);
    const [x0, y0, z0, x1, y1, z1] = scene.bounds();
    const o = [(x0 + x1) / 2, (y0 + y1) / 2, z1 + 10 * (z1 - z0 + 1)];
    const h = scene.raycastFirst(o[0], o[1], o[2], 0, 0, -1);
    assert.ok(h === undefined || (h.t > 0 && h.primitive < scene.triangleCount));
  });
  scene.free();
}
bvh.free();
console.log(`api: ${checks} checks passed`);
