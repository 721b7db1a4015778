/* Traces the rays of a `bvhtrace dump` file with Embree 3 (robust mode), so our hit counts
 * and speed can be compared with an independent tracer on exactly the same rays.
 *
 *   cc -O2 embree_trace.c -lembree3 -lpthread -lm -o embree_trace
 *   embree_trace DUMP [THREADS] [RUNS] [HITS_OUT] [T_OUT]
 *
 * Against Embree 4 (its API: no intersect context, optional arguments), with its headers in
 * E4/include and its library at E4/libembree4.so.4 (docs/cpu-tracer.md says how to get 4.4):
 *
 *   cc -O2 -DBVHTRACE_EMBREE4 -IE4/include embree_trace.c E4/libembree4.so.4 \
 *     -Wl,-rpath,E4 -lpthread -lm -o embree4_trace
 *
 * Prints one JSON object: triangles, rays, hits, t_sum, build_ms and trace_ms (medians of
 * RUNS), mrays_per_s. With BVHTRACE_REFIT=A in the environment it also times a refit
 * (RTC_BUILD_QUALITY_REFIT) after moving every vertex by `bvhtrace bench-refit`'s field of
 * amplitude A (`deform` in crates/cli/src/bench/refit.rs): refit_ms, the median of RUNS.
 * BVHTRACE_EMBREE_MODE=fast drops RTC_SCENE_FLAG_ROBUST (Embree's default, not watertight);
 * BVHTRACE_EMBREE_QUERY=any traces occlusion (rtcOccluded1: hits counts occluded rays,
 * t_sum is 0). HITS_OUT, if given, receives one u32 primitive index per ray
 * (0xFFFFFFFF for a miss). Dump format (little endian): "BVHD", u32 version = 1, u32 n_tris,
 * u32 n_rays, n_tris * 9 f32 corners, n_rays * 8 f32 rays (origin, t_min, dir, t_max).
 * Version 2 (`bvhtrace dump --shutter`) is a moving mesh: after n_rays a u32 time step count
 * S, then S * n_tris * 9 f32 corners (step 0's triangles first), the rays, and n_rays f32
 * times; the triangles get S time steps (rtcSetGeometryTimeStepCount) and each ray its
 * time. Version 3 (`bvhtrace dump --shutter --instances`) is meshes under moving instances:
 * after n_rays (here the mesh count M is in n_tris' place) a u32 instance count I and the
 * u32 step count S; M meshes, each a u32 triangle count and its 9 f32 corners per
 * triangle; I instances, each a u32 mesh, a u32 transform count (1 or S) and 12 f32 per
 * transform (3x4, column major); the rays; n_rays f32 times. Each instance is an Embree
 * instance of its mesh's scene with its transforms as time steps; a hit reports the
 * instance's first primitive (the flattened scene's numbering) plus the mesh's. Version 4
 * (`bvhtrace dump builtin:hair`) adds curves beside the triangles: after n_rays a u32
 * curve kind (0 round linear, 1 flat linear, 2 round Bezier, 3 round B-spline), a u32
 * point count P and a u32 segment count C; after the triangles P * 4 f32 points (xyz,
 * radius), C u32 first points, C u8 neighbour flags (RTC_CURVE_FLAG_NEIGHBOR_LEFT = 1,
 * RIGHT = 2), then the rays. A curve hit reports n_tris plus its segment. T_OUT, a fifth
 * argument, receives two f32 per ray: the hit's t and u (0 for a miss). */
#ifdef BVHTRACE_EMBREE4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct { float org[3], tmin, dir[3], tmax; } Ray;

static RTCScene scene;
static const Ray *rays;
static const float *times;
static uint32_t n_rays, n_threads;
static uint32_t *hit_prim;
static float *hit_t;
static int occlusion;

/* Version 3's meshes and moving instances, and each instance's first primitive id. */
typedef struct { uint32_t n_tris; float *tris; } Mesh;
typedef struct { uint32_t mesh, steps; float *xfm; } Instance;
static Mesh *meshes;
static Instance *insts;
static uint32_t n_meshes, n_insts, *first_ids;

/* Version 4's curves. */
static const enum RTCGeometryType curve_types[4] = {
    RTC_GEOMETRY_TYPE_ROUND_LINEAR_CURVE, RTC_GEOMETRY_TYPE_FLAT_LINEAR_CURVE,
    RTC_GEOMETRY_TYPE_ROUND_BEZIER_CURVE, RTC_GEOMETRY_TYPE_ROUND_BSPLINE_CURVE};
static uint32_t curve_kind, n_points, n_segments, n_tris_global;
static float *points, *hit_u;
static uint32_t *segments;
static uint8_t *seg_flags;

static double now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

static void *worker(void *arg) {
  uintptr_t id = (uintptr_t)arg;
  uint32_t chunk = (n_rays + n_threads - 1) / n_threads;
  uint32_t lo = id * chunk, hi = lo + chunk > n_rays ? n_rays : lo + chunk;
#ifndef BVHTRACE_EMBREE4
  struct RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
#endif
  for (uint32_t i = lo; i < hi; i++) {
    const Ray *r = &rays[i];
    struct RTCRayHit rh;
    rh.ray.org_x = r->org[0]; rh.ray.org_y = r->org[1]; rh.ray.org_z = r->org[2];
    rh.ray.dir_x = r->dir[0]; rh.ray.dir_y = r->dir[1]; rh.ray.dir_z = r->dir[2];
    rh.ray.tnear = r->tmin; rh.ray.tfar = r->tmax;
    rh.ray.mask = 0xFFFFFFFF; rh.ray.flags = 0; rh.ray.time = times ? times[i] : 0.0f;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    if (occlusion) {
      /* An occluded ray comes back with tfar = -inf; the primitive is not reported. */
#ifdef BVHTRACE_EMBREE4
      rtcOccluded1(scene, &rh.ray, NULL);
#else
      rtcOccluded1(scene, &ctx, &rh.ray);
#endif
      hit_prim[i] = rh.ray.tfar < 0.0f ? 0u : 0xFFFFFFFFu;
      hit_t[i] = 0.0f;
      continue;
    }
#ifdef BVHTRACE_EMBREE4
    rtcIntersect1(scene, &rh, NULL);
#else
    rtcIntersect1(scene, &ctx, &rh);
#endif
    int hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
    uint32_t base = first_ids && hit ? first_ids[rh.hit.instID[0]] : 0;
    if (hit && points && rh.hit.geomID == 1) base = n_tris_global;
    hit_prim[i] = hit ? base + rh.hit.primID : 0xFFFFFFFFu;
    hit_t[i] = hit ? rh.ray.tfar : 0.0f;
    hit_u[i] = hit ? rh.hit.u : 0.0f;
  }
  return NULL;
}

/* A committed triangle-soup geometry of `n` triangles (9 floats each) at `steps` time
 * steps (step k's triangles at tris + 9 n k), built with `quality`; `*vertices` (when not
 * NULL) receives step 0's vertex buffer. */
static RTCGeometry soup(RTCDevice dev, const float *tris, uint32_t n, uint32_t steps, enum RTCBuildQuality quality, float **vertices) {
  RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
  rtcSetGeometryBuildQuality(g, quality);
  if (steps > 1) rtcSetGeometryTimeStepCount(g, steps);
  float *v = NULL;
  for (uint32_t k = 0; k < steps; k++) {
    float *vk = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, k, RTC_FORMAT_FLOAT3, 12, 3 * (size_t)n);
    memcpy(vk, tris + 9 * (size_t)n * k, 36 * (size_t)n);
    if (k == 0) v = vk;
  }
  unsigned *ix = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, n);
  for (uint32_t i = 0; i < 3 * n; i++) ix[i] = i;
  rtcCommitGeometry(g);
  if (vertices) *vertices = v;
  return g;
}

/* Version 3's meshes and instances from `f` (after the header); 0 on success. */
static int read_instances(FILE *f, uint32_t steps) {
  meshes = calloc(n_meshes, sizeof(Mesh));
  insts = calloc(n_insts, sizeof(Instance));
  first_ids = calloc(n_insts ? n_insts : 1, 4);
  if (!meshes || !insts || !first_ids) return 1;
  for (uint32_t m = 0; m < n_meshes; m++) {
    if (fread(&meshes[m].n_tris, 4, 1, f) != 1) return 1;
    size_t n = 9 * (size_t)meshes[m].n_tris;
    meshes[m].tris = malloc(4 * n + 4);
    if (!meshes[m].tris || fread(meshes[m].tris, 4, n, f) != n) return 1;
  }
  uint32_t next = 0;
  for (uint32_t i = 0; i < n_insts; i++) {
    Instance *in = &insts[i];
    if (fread(&in->mesh, 4, 1, f) != 1 || fread(&in->steps, 4, 1, f) != 1 || in->mesh >= n_meshes ||
        (in->steps != 1 && in->steps != steps))
      return 1;
    in->xfm = malloc(48 * (size_t)in->steps);
    if (!in->xfm || fread(in->xfm, 48, in->steps, f) != in->steps) return 1;
    first_ids[i] = next;
    next += meshes[in->mesh].n_tris;
  }
  return 0;
}

/* Version 3's scene: one scene per mesh, one instance geometry per instance (geometry id =
 * instance index) with its transforms as time steps. */
static RTCScene instanced_scene(RTCDevice dev, int robust) {
  RTCScene top = rtcNewScene(dev);
  rtcSetSceneFlags(top, robust ? RTC_SCENE_FLAG_ROBUST : RTC_SCENE_FLAG_NONE);
  rtcSetSceneBuildQuality(top, RTC_BUILD_QUALITY_MEDIUM);
  RTCScene *mesh_scenes = malloc(sizeof(RTCScene) * (n_meshes ? n_meshes : 1));
  for (uint32_t m = 0; m < n_meshes; m++) {
    mesh_scenes[m] = rtcNewScene(dev);
    rtcSetSceneFlags(mesh_scenes[m], robust ? RTC_SCENE_FLAG_ROBUST : RTC_SCENE_FLAG_NONE);
    RTCGeometry g = soup(dev, meshes[m].tris, meshes[m].n_tris, 1, RTC_BUILD_QUALITY_MEDIUM, NULL);
    rtcAttachGeometry(mesh_scenes[m], g);
    rtcReleaseGeometry(g);
    rtcCommitScene(mesh_scenes[m]);
  }
  for (uint32_t i = 0; i < n_insts; i++) {
    RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_INSTANCE);
    rtcSetGeometryInstancedScene(g, mesh_scenes[insts[i].mesh]);
    if (insts[i].steps > 1) rtcSetGeometryTimeStepCount(g, insts[i].steps);
    for (uint32_t k = 0; k < insts[i].steps; k++)
      rtcSetGeometryTransform(g, k, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, insts[i].xfm + 12 * k);
    rtcCommitGeometry(g);
    rtcAttachGeometryByID(top, g, i);
    rtcReleaseGeometry(g);
  }
  rtcCommitScene(top);
  for (uint32_t m = 0; m < n_meshes; m++) rtcReleaseScene(mesh_scenes[m]);
  free(mesh_scenes);
  return top;
}

/* Version 4's curves from `f` (after the triangles); 0 on success. */
static int read_curves(FILE *f) {
  points = malloc(16 * (size_t)n_points + 16);
  segments = malloc(4 * (size_t)n_segments + 4);
  seg_flags = malloc((size_t)n_segments + 1);
  if (!points || !segments || !seg_flags || curve_kind > 3) return 1;
  if (fread(points, 16, n_points, f) != n_points || fread(segments, 4, n_segments, f) != n_segments ||
      fread(seg_flags, 1, n_segments, f) != n_segments)
    return 1;
  uint32_t degree = curve_kind < 2 ? 1 : 3;
  for (uint32_t i = 0; i < n_segments; i++)
    if ((uint64_t)segments[i] + degree >= n_points) return 1;
  return 0;
}

/* Version 4's curve geometry, attached to `s` as geometry 1. */
static void attach_curves(RTCDevice dev, RTCScene s) {
  RTCGeometry g = rtcNewGeometry(dev, curve_types[curve_kind]);
  float *v = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT4, 16, n_points);
  memcpy(v, points, 16 * (size_t)n_points);
  unsigned *ix = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT, 4, n_segments);
  memcpy(ix, segments, 4 * (size_t)n_segments);
  if (curve_kind < 2) {
    uint8_t *fl = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_FLAGS, 0, RTC_FORMAT_UCHAR, 1, n_segments);
    memcpy(fl, seg_flags, n_segments);
  }
  rtcCommitGeometry(g);
  rtcAttachGeometryByID(s, g, 1);
  rtcReleaseGeometry(g);
}

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

int main(int argc, char **argv) {
  if (argc < 2) {
    fprintf(stderr, "usage: %s DUMP [THREADS] [RUNS] [HITS_OUT] [T_OUT]\n", argv[0]);
    return 2;
  }
  n_threads = argc > 2 ? (uint32_t)atoi(argv[2]) : 2;
  const char *mode = getenv("BVHTRACE_EMBREE_MODE"), *query = getenv("BVHTRACE_EMBREE_QUERY");
  int robust = !(mode && strcmp(mode, "fast") == 0);
  occlusion = query && strcmp(query, "any") == 0;
  int runs = argc > 3 ? atoi(argv[3]) : 5;
  if (n_threads < 1) n_threads = 1;
  if (runs < 1) runs = 1;
  FILE *f = fopen(argv[1], "rb");
  if (!f) { perror(argv[1]); return 1; }
  char magic[4];
  uint32_t hdr[3];
  uint32_t steps = 1;
  if (fread(magic, 1, 4, f) != 4 || memcmp(magic, "BVHD", 4) || fread(hdr, 4, 3, f) != 3 || hdr[0] < 1 || hdr[0] > 4 ||
      (hdr[0] == 3 && fread(&n_insts, 4, 1, f) != 1) ||
      (hdr[0] == 4 && (fread(&curve_kind, 4, 1, f) != 1 || fread(&n_points, 4, 1, f) != 1 || fread(&n_segments, 4, 1, f) != 1)) ||
      ((hdr[0] == 2 || hdr[0] == 3) && (fread(&steps, 4, 1, f) != 1 || steps < 2 || steps > RTC_MAX_TIME_STEP_COUNT))) {
    fprintf(stderr, "%s: not a bvhtrace dump (version 1 to 4)\n", argv[1]);
    return 1;
  }
  uint32_t n_tris = hdr[1];
  n_rays = hdr[2];
  if (hdr[0] == 3) {
    n_meshes = n_tris;
    n_tris = 0;
    if (read_instances(f, steps)) {
      fprintf(stderr, "%s: truncated or bad instances\n", argv[1]);
      return 1;
    }
  }
  size_t n_corners = 9 * (size_t)n_tris * steps;
  float *tris = malloc(sizeof(float) * n_corners);
  Ray *r = malloc(sizeof(Ray) * (size_t)n_rays);
  float *ray_times = steps > 1 ? malloc(4 * (size_t)n_rays) : NULL;
  hit_prim = malloc(4 * (size_t)n_rays);
  hit_t = malloc(4 * (size_t)n_rays);
  hit_u = malloc(4 * (size_t)n_rays);
  n_tris_global = n_tris;
  if (!tris || !r || !hit_prim || !hit_t || !hit_u || (steps > 1 && !ray_times) || fread(tris, 4, n_corners, f) != n_corners ||
      (hdr[0] == 4 && read_curves(f)) ||
      fread(r, sizeof(Ray), n_rays, f) != n_rays || (ray_times && fread(ray_times, 4, n_rays, f) != n_rays)) {
    fprintf(stderr, "%s: truncated dump\n", argv[1]);
    return 1;
  }
  fclose(f);
  rays = r;
  times = ray_times;

  char cfg[64];
  snprintf(cfg, sizeof cfg, "threads=%u", n_threads);
  RTCDevice dev = rtcNewDevice(cfg);
  double *build = malloc(sizeof(double) * runs), *trace = malloc(sizeof(double) * runs);
  for (int run = 0; run < runs; run++) {
    double t0 = now_ms();
    if (insts) {
      scene = instanced_scene(dev, robust);
    } else {
      scene = rtcNewScene(dev);
      rtcSetSceneFlags(scene, robust ? RTC_SCENE_FLAG_ROBUST : RTC_SCENE_FLAG_NONE);
      rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_MEDIUM);
      if (n_tris) {
        RTCGeometry g = soup(dev, tris, n_tris, steps, RTC_BUILD_QUALITY_MEDIUM, NULL);
        rtcAttachGeometryByID(scene, g, 0);
        rtcReleaseGeometry(g);
      }
      if (points) attach_curves(dev, scene);
      rtcCommitScene(scene);
    }
    build[run] = now_ms() - t0;

    pthread_t th[64];
    uint32_t nt = n_threads > 64 ? 64 : n_threads;
    n_threads = nt;
    double t1 = now_ms();
    for (uintptr_t i = 0; i < nt; i++) pthread_create(&th[i], NULL, worker, (void *)i);
    for (uint32_t i = 0; i < nt; i++) pthread_join(th[i], NULL);
    trace[run] = now_ms() - t1;
    if (run + 1 < runs) rtcReleaseScene(scene);
  }
  qsort(build, runs, sizeof(double), cmp);
  qsort(trace, runs, sizeof(double), cmp);
  uint64_t hits = 0;
  double t_sum = 0;
  for (uint32_t i = 0; i < n_rays; i++)
    if (hit_prim[i] != 0xFFFFFFFFu) { hits++; t_sum += hit_t[i]; }
  if (argc > 4) {
    FILE *o = fopen(argv[4], "wb");
    if (!o || fwrite(hit_prim, 4, n_rays, o) != n_rays) { perror(argv[4]); return 1; }
    fclose(o);
  }
  if (argc > 5) {
    FILE *o = fopen(argv[5], "wb");
    for (uint32_t i = 0; o && i < n_rays; i++)
      if (fwrite(&hit_t[i], 4, 1, o) != 1 || fwrite(&hit_u[i], 4, 1, o) != 1) { fclose(o); o = NULL; }
    if (!o) { perror(argv[5]); return 1; }
    fclose(o);
  }
  double refit_ms = -1;
  const char *refit_env = getenv("BVHTRACE_REFIT");
  if (refit_env) {
    /* The deformation of bench/refit.rs: p + a*e*(sin(k y), sin(k z), sin(k x)), k = 6/e. */
    float a = (float)atof(refit_env), lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t i = 0; i < 3 * (size_t)n_tris; i++)
      for (int c = 0; c < 3; c++) {
        float x = tris[3 * i + c];
        lo[c] = x < lo[c] ? x : lo[c];
        hi[c] = x > hi[c] ? x : hi[c];
      }
    float e = hi[0] - lo[0];
    if (hi[1] - lo[1] > e) e = hi[1] - lo[1];
    if (hi[2] - lo[2] > e) e = hi[2] - lo[2];
    float k = 6.0f / e;
    float *moved = malloc(36 * (size_t)n_tris);
    for (size_t i = 0; i < 3 * (size_t)n_tris; i++) {
      const float *p = &tris[3 * i];
      moved[3 * i] = p[0] + sinf(k * p[1]) * (a * e);
      moved[3 * i + 1] = p[1] + sinf(k * p[2]) * (a * e);
      moved[3 * i + 2] = p[2] + sinf(k * p[0]) * (a * e);
    }
    double *refit = malloc(sizeof(double) * runs);
    for (int run = 0; run < runs; run++) {
      RTCScene rs = rtcNewScene(dev);
      rtcSetSceneFlags(rs, RTC_SCENE_FLAG_ROBUST | RTC_SCENE_FLAG_DYNAMIC);
      float *v;
      RTCGeometry g = soup(dev, tris, n_tris, 1, RTC_BUILD_QUALITY_REFIT, &v);
      rtcAttachGeometry(rs, g);
      rtcCommitScene(rs);
      /* Timed: the vertices move, the geometry and the scene are committed again. */
      double t0 = now_ms();
      memcpy(v, moved, 36 * (size_t)n_tris);
      rtcUpdateGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0);
      rtcCommitGeometry(g);
      rtcCommitScene(rs);
      refit[run] = now_ms() - t0;
      rtcReleaseGeometry(g);
      rtcReleaseScene(rs);
    }
    qsort(refit, runs, sizeof(double), cmp);
    refit_ms = refit[runs / 2];
    free(moved);
    free(refit);
  }
  double tm = trace[runs / 2];
  printf("{\"tracer\": \"embree %d.%d.%d %s, medium build%s\", \"threads\": %u, \"triangles\": %u, \"time_steps\": %u, \"rays\": %u, "
         "\"hits\": %llu, \"t_sum\": %.6f, \"build_ms\": %.3f, \"trace_ms\": %.3f, \"mrays_per_s\": %.3f, "
         "\"refit_ms\": %.3f}\n",
         RTC_VERSION_MAJOR, RTC_VERSION_MINOR, RTC_VERSION_PATCH, robust ? "robust" : "fast",
         occlusion ? ", occlusion" : "", n_threads, n_tris, steps, n_rays,
         (unsigned long long)hits, t_sum, build[runs / 2], tm, n_rays / tm / 1e3, refit_ms);
  rtcReleaseScene(scene);
  rtcReleaseDevice(dev);
  return 0;
}
