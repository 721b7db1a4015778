// One thread of BvhWorkers (workers.js): the module, a copy of the tree, and the rays
// it is sent.
import init, { Bvh } from "./bvhtrace_web.js";

let bvh = null;
onmessage = async ({ data }) => {
  try {
    if (data.build) {
      // buildInWorker: the tree built here, off the page's thread, and sent back as bytes.
      await init();
      const built = new Bvh(data.build.positions, data.build.indices);
      const tree = built.toBytes();
      built.free();
      postMessage({ tree }, [tree.buffer]);
      return;
    }
    if (data.tree) {
      await init();
      bvh?.free();
      bvh = Bvh.fromBytes(data.tree);
      postMessage({ ready: true });
      return;
    }
    const h = bvh.intersect(data.origins, data.directions, data.options);
    const { t, primitive, u, v } = h;
    postMessage({ id: data.id, hits: h }, [t.buffer, primitive.buffer, u.buffer, v.buffer]);
  } catch (e) {
    postMessage({ id: data.id, error: String(e && e.message || e) });
  }
};
