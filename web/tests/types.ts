// A program written from the package's README, compiled by tsc (web/package.sh) against
// the declarations the package ships: the types must describe what the README promises.
import init, { Bvh, InstancedBvh, type Hits, type Hit, type InstancedHits, type TraceOptions } from "bvhtrace";
import { computeBvh, raycastFirst, acceleratedRaycast, type GeometryLike } from "bvhtrace/three";
import { BvhWorkers, buildInWorker } from "bvhtrace/workers";

export async function example(geometry: GeometryLike): Promise<number> {
  await init();
  const positions = new Float32Array([0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0]);
  const bvh = new Bvh(positions, new Uint32Array([0, 1, 2, 0, 2, 3]));
  const hit: Hit | undefined = bvh.raycastFirst(0.25, 0.75, 5, 0, 0, -1);
  const options: TraceOptions = { anyHit: true, far: 1 };
  const hits: Hits = bvh.intersect(new Float32Array(3), new Float32Array([0, 0, -1]), options);
  const first: number = hits.primitive[0] + hits.t[0] + hits.hitCount;
  const onDevice = await Bvh.create(positions, undefined, { backend: "auto" });
  const later: Hits = await onDevice.intersectAsync(new Float32Array(3), new Float32Array(3));
  const note: string = onDevice.backend + onDevice.backendNote + later.backend;
  bvh.refit(positions);
  const wgsl = bvh.wgsl(0);
  const bytes: number = wgsl.bindings[0].data.byteLength + wgsl.source.length + wgsl.stackLanes;
  const scene = new InstancedBvh();
  scene.addInstance(scene.addMesh(bvh), new Float32Array(16));
  const placed: InstancedHits = scene.intersect(new Float32Array(3), new Float32Array(3));
  const which: number = placed.instance[0] + placed.meshPrimitive[0] + scene.instanceCount;
  scene.free();
  const copy: Bvh = await buildInWorker(positions);
  Bvh.fromBytes(copy.toBytes()).free();
  const pool = await BvhWorkers.create(copy, 2);
  const parallel: Hits = await pool.intersect(new Float32Array(3), new Float32Array(3), { near: 0 });
  pool.terminate();
  copy.free();
  const three = computeBvh(geometry);
  const fallback = (_raycaster: unknown, _intersects: unknown[]) => {};
  const raycast = acceleratedRaycast(fallback);
  const none = raycastFirst({}, {}) === null;
  bvh.free();
  onDevice.free();
  three.free();
  return bytes + which + parallel.count + first + (hit ? hit.t + hit.point[0] : 0) + note.length + (none ? 1 : 0) + raycast.length;
}
