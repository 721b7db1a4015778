// Our hits against three-mesh-bvh's `raycastFirst`, ray for ray, in Node (one thread each):
// a camera's rays over each glTF scene given, our Bvh built the way a three.js user builds
// it (web/package/three.js's computeBvh over the scene's meshes merged into one
// BufferGeometry), three-mesh-bvh's MeshBVH over the same geometry. Prints one line per
// scene and exits non-zero when a ray's answers differ beyond the rule below.
//
// usage: node web/tests/three.mjs PKG_DIR SCENE... [--size WxH]
//
// The rule: both miss, or both hit the same triangle at distances within 1e-5 relative,
// or both hit different triangles at such a distance (a ray through a shared edge or
// corner: each library takes one of the triangles there). three-mesh-bvh's test is not
// watertight, so a ray through an edge may hit in one library and miss in the other; such
// rays are counted and allowed only when a ray within a hundredth of a pixel agrees.
import fs from "node:fs";
import path from "node:path";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { mergeGeometries } from "three/examples/jsm/utils/BufferGeometryUtils.js";
import { MeshBVH } from "three-mesh-bvh";

// three's FileLoader (a .gltf's data URIs) reports progress with the DOM's ProgressEvent.
globalThis.ProgressEvent ??= class extends Event {
  constructor(type, init = {}) {
    super(type);
    Object.assign(this, { lengthComputable: false, loaded: 0, total: 0 }, init);
  }
};

const args = process.argv.slice(2);
const sizeAt = args.indexOf("--size");
const [W, H] = sizeAt >= 0 ? args.splice(sizeAt, 2)[1].split("x").map(Number) : [512, 384];
const [pkg, ...scenes] = args;
const { default: init, Bvh } = await import(path.resolve(pkg, "bvhtrace_web.js"));
const { computeBvh } = await import(path.resolve(pkg, "three.js"));
await init({ module_or_path: fs.readFileSync(path.resolve(pkg, "bvhtrace_web_bg.wasm")) });

/** The scene's meshes, world transforms applied, merged into one position-only geometry. */
async function geometryOf(file) {
  const bytes = fs.readFileSync(file);
  const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  const gltf = await new GLTFLoader().parseAsync(buffer, path.dirname(file) + "/");
  gltf.scene.updateMatrixWorld(true);
  const parts = [];
  gltf.scene.traverse((o) => {
    if (!o.isMesh) return;
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", o.geometry.getAttribute("position").clone());
    const index = o.geometry.getIndex();
    g.setIndex(index ? Array.from(index.array) : [...Array(g.getAttribute("position").count).keys()]);
    g.applyMatrix4(o.matrixWorld);
    parts.push(g);
  });
  return mergeGeometries(parts);
}

/** Camera rays through the box's centre from the front, W x H pixels, origins and unit directions. */
function cameraRays(geometry, w, h, jitter = 0) {
  geometry.computeBoundingBox();
  const box = geometry.boundingBox;
  const c = box.getCenter(new THREE.Vector3());
  const r = box.getSize(new THREE.Vector3()).length();
  const eye = new THREE.Vector3(c.x + 0.3 * r, c.y + 0.2 * r, c.z + 1.6 * r);
  const cam = new THREE.PerspectiveCamera(40, w / h, 0.01, 100);
  cam.position.copy(eye);
  cam.lookAt(c);
  cam.updateMatrixWorld();
  const origins = new Float32Array(3 * w * h), dirs = new Float32Array(3 * w * h);
  const d = new THREE.Vector3();
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const i = 3 * (y * w + x);
      d.set(((x + 0.5 + jitter) / w) * 2 - 1, 1 - ((y + 0.5 + jitter) / h) * 2, 0.5)
        .unproject(cam).sub(eye).normalize();
      origins.set([eye.x, eye.y, eye.z], i);
      dirs.set([d.x, d.y, d.z], i);
    }
  }
  return { origins, dirs };
}

/** three-mesh-bvh's answers for the rays: distance (Infinity for a miss) and faceIndex. */
function threeHits(bvh, origins, dirs) {
  const n = origins.length / 3;
  const t = new Float64Array(n), face = new Int32Array(n);
  const ray = new THREE.Ray();
  for (let i = 0; i < n; i++) {
    ray.origin.fromArray(origins, 3 * i);
    ray.direction.fromArray(dirs, 3 * i);
    const h = bvh.raycastFirst(ray, THREE.DoubleSide);
    t[i] = h ? h.distance : Infinity;
    face[i] = h ? h.faceIndex : -1;
  }
  return { t, face };
}

/** Milliseconds `f` takes, best of `runs`. */
function best(runs, f) {
  let ms = Infinity, out;
  for (let k = 0; k < runs; k++) {
    const t0 = performance.now();
    out = f();
    ms = Math.min(ms, performance.now() - t0);
  }
  return { ms, out };
}

let failed = false;
for (const file of scenes) {
  const name = path.basename(file);
  const geometry = await geometryOf(file);
  // MeshBVH reorders the geometry's index (its faceIndex is the new order): ours is built
  // over the geometry as it leaves it, so that both name triangles alike.
  const theirs = new MeshBVH(geometry);
  const ours = computeBvh(geometry);
  const { origins, dirs } = cameraRays(geometry, W, H);
  const n = origins.length / 3;
  const a = best(3, () => ours.intersect(origins, dirs));
  const single = best(3, () => {
    let hits = 0;
    for (let i = 0; i < n; i++) {
      const j = 3 * i;
      const o = origins, d = dirs;
      if (ours.raycastFirst(o[j], o[j + 1], o[j + 2], d[j], d[j + 1], d[j + 2])) hits++;
    }
    return hits;
  });
  const b = best(3, () => threeHits(theirs, origins, dirs));
  const h = a.out, th = b.out;
  let same = 0, tie = 0, edge = 0, differ = 0, ourHits = 0, theirHits = 0;
  const retry = [];
  for (let i = 0; i < n; i++) {
    const ourHit = h.primitive[i] !== 0xffffffff, theirHit = th.face[i] >= 0;
    ourHits += ourHit;
    theirHits += theirHit;
    if (!ourHit && !theirHit) { same++; continue; }
    if (ourHit && theirHit && Math.abs(h.t[i] - th.t[i]) <= 1e-5 * th.t[i]) {
      if (h.primitive[i] === th.face[i]) same++; else tie++;
      continue;
    }
    retry.push(i);
  }
  // A ray one library hits and the other misses, or whose distances differ, passed
  // within rounding of an edge when a ray a hundredth of a pixel away agrees.
  if (retry.length) {
    const near = cameraRays(geometry, W, H, 0.01);
    for (const i of retry) {
      const o = near.origins.subarray(3 * i, 3 * i + 3), d = near.dirs.subarray(3 * i, 3 * i + 3);
      const mine = ours.raycastFirst(...o, ...d);
      const ray = new THREE.Ray(new THREE.Vector3().fromArray(o), new THREE.Vector3().fromArray(d));
      const other = theirs.raycastFirst(ray, THREE.DoubleSide);
      const agree = (!mine && !other) || (mine && other && Math.abs(mine.t - other.distance) <= 1e-5 * other.distance);
      if (agree) edge++; else differ++;
    }
  }
  const rate = (ms) => (n / ms / 1e3).toFixed(2);
  console.log(
    `three.js parity (${name}, ${geometry.index.count / 3} triangles): ${n} rays, hits ${ourHits} ` +
    `(three-mesh-bvh ${theirHits}); same ${same}, a tie at a shared edge ${tie}, through an edge ` +
    `${edge}, ${differ} differ; Mrays/s on one thread: bvhtrace intersect ${rate(a.ms)} ` +
    `(${h.backend}), raycastFirst ${rate(single.ms)}, three-mesh-bvh raycastFirst ${rate(b.ms)} ` +
    `(${(b.ms / a.ms).toFixed(2)}x, ${(b.ms / single.ms).toFixed(2)}x)`,
  );
  if (differ > 0 || edge > n / 1000) failed = true;
  ours.free();
}
process.exit(failed ? 1 : 0);
