// The core as XLA FFI targets for the CPU (jax.ffi), and the Python module
// that hands them to JAX (pmjax/engines/_core.py registers them).
//
// Every target checks its buffers against the hierarchy they claim to come
// from (shapes, capacities) and returns an error naming the argument, so a
// mismatch is a Python exception, never a write past a buffer. Operands and
// results, in order, are listed above each binding; pmjax/engines/_core.py
// calls them in that order.

#include <Python.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "pmx.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// The sizes of an array, for messages: "[436325, 16]".
std::string Shape(ffi::Span<const int64_t> dims) {
  std::string s = "[";
  for (size_t i = 0; i < dims.size(); ++i) s += (i ? ", " : "") + std::to_string(dims[i]);
  return s + "]";
}

// An error unless `dims` equals `want`.
ffi::Error Expect(const char* name, ffi::Span<const int64_t> dims, std::initializer_list<int64_t> want) {
  bool same = dims.size() == want.size() && std::equal(want.begin(), want.end(), dims.begin());
  if (same) return ffi::Error::Success();
  std::string w = "[";
  size_t i = 0;
  for (int64_t d : want) w += (i++ ? ", " : "") + std::to_string(d);
  return ffi::Error::InvalidArgument(std::string(name) + " must have shape " + w + "], got " + Shape(dims));
}

#define PMX_CHECK(expr)                          \
  do {                                           \
    ffi::Error pmx_error = (expr);               \
    if (pmx_error.failure()) return pmx_error;   \
  } while (0)

// The hierarchy's tables: rows [P, PMX_ROW], kills [P], order [P] (the
// checks of the XLA targets and of the eager entry alike).
ffi::Error HierarchyOf(const float* rows, ffi::Span<const int64_t> rows_dims, const int32_t* kills,
                       ffi::Span<const int64_t> kills_dims, const int32_t* order,
                       ffi::Span<const int64_t> order_dims, int64_t n_roots, PmxHierarchy* h) {
  if (rows_dims.size() != 2 || rows_dims[1] != PMX_ROW)
    return ffi::Error::InvalidArgument("rows must have shape [P, " + std::to_string(PMX_ROW) + "], got " +
                                       Shape(rows_dims));
  const int64_t P = rows_dims[0];
  PMX_CHECK(Expect("kills", kills_dims, {P}));
  PMX_CHECK(Expect("order", order_dims, {P}));
  if (P > PMX_MAX_PCOLS || n_roots < 0 || n_roots > P || (P > 0 && n_roots == 0))
    return ffi::Error::InvalidArgument("n_roots " + std::to_string(n_roots) + " does not fit " + std::to_string(P) +
                                       " pcols");
  if (reinterpret_cast<uintptr_t>(rows) % 4 != 0) return ffi::Error::InvalidArgument("rows are not aligned");
  *h = PmxHierarchy{rows, kills, order, P, n_roots};
  return ffi::Error::Success();
}

ffi::Error Hierarchy(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills, ffi::Buffer<ffi::S32> order,
                     int64_t n_roots, PmxHierarchy* h) {
  return HierarchyOf(rows.typed_data(), rows.dimensions(), kills.typed_data(), kills.dimensions(),
                     order.typed_data(), order.dimensions(), n_roots, h);
}

ffi::Error Status(PmxStatus status, const char* what) {
  if (status == PMX_OK) return ffi::Error::Success();
  return ffi::Error(status == PMX_NO_MEMORY ? ffi::ErrorCode::kResourceExhausted : ffi::ErrorCode::kInvalidArgument,
                    std::string(what) + ": " + pmx_status_text(status));
}

// A list result: [n] or [batch, n] with n = P + PMX_SPARE, or empty (not wanted).
ffi::ErrorOr<bool> ListWanted(const char* name, ffi::Span<const int64_t> dims, int64_t batch, int64_t P) {
  int64_t count = 1;
  for (int64_t d : dims) count *= d;
  if (count == 0) return false;
  bool ok = batch < 0 ? dims.size() == 1 && dims[0] == P + PMX_SPARE
                      : dims.size() == 2 && dims[0] == batch && dims[1] == P + PMX_SPARE;
  if (!ok)
    return ffi::Unexpected(ffi::Error::InvalidArgument(std::string(name) + " must be empty or have " +
                                                       std::to_string(P + PMX_SPARE) + " slots per item, got " +
                                                       Shape(dims)));
  return true;
}

// XLA's CPU thread pool as the core's runner.
void Schedule(void* ctx, void (*task)(void*), void* arg) {
  static_cast<ffi::ThreadPool*>(ctx)->Schedule([task, arg] { task(arg); });
}

PmxRunner Runner(ffi::ThreadPool& pool, int64_t threads) {
  int64_t have = std::max<int64_t>(1, pool.num_threads());
  return PmxRunner{Schedule, &pool, threads > 0 ? std::min(threads, have) : have};
}

// One scratch from the pool for the length of a call.
struct Scratch {
  PmxScratch* s;
  explicit Scratch(int64_t n_pcols) : s(pmx_scratch_take(n_pcols)) {}
  ~Scratch() {
    if (s) pmx_scratch_give(s);
  }
};

// ---- one camera ------------------------------------------------------------
// The lists of one camera: pcols s32[L], ran u8[L], positions s32[L] (L = P + PMX_SPARE, or 0: counts only).
ffi::ErrorOr<PmxLists> OneLists(int64_t P, ffi::Result<ffi::Buffer<ffi::S32>>& pcols,
                                ffi::Result<ffi::Buffer<ffi::U8>>& ran, ffi::Result<ffi::Buffer<ffi::S32>>& positions) {
  for (auto [name, dims] : {std::pair{"pcols", pcols->dimensions()}, std::pair{"ran", ran->dimensions()},
                            std::pair{"positions", positions->dimensions()}}) {
    auto wanted = ListWanted(name, dims, -1, P);
    if (wanted.has_error()) return ffi::Unexpected(wanted.error());
  }
  PmxLists lists{};
  if (pcols->element_count()) lists.pcols = pcols->typed_data();
  if (ran->element_count()) lists.ran = ran->typed_data();
  if (positions->element_count()) lists.positions = positions->typed_data();
  return lists;
}

void PutCounts(const PmxCounts& c, int level, int32_t* out) {
  out[0] = c.visited, out[1] = c.not_run, out[2] = c.kept, out[3] = c.unsure, out[4] = level;
}

// The first pass: unsure decisions taken as "keep" and listed.
// operands: rows f32[P,16], kills s32[P], order s32[P], camera f32[PMX_CAMERA] (with tau)
// results: pcols s32[L], ran u8[L], positions s32[L], unsure s32[P + PMX_SPARE] (positions, increasing),
//          yes s32[P + PMX_SPARE] (not written: room for the caller's answers),
//          counts s32[5] (visited, not run, kept, unsure, SIMD level)
ffi::Error RefineOne(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills, ffi::Buffer<ffi::S32> order,
                     ffi::Buffer<ffi::F32> camera, ffi::ResultBuffer<ffi::S32> pcols, ffi::ResultBuffer<ffi::U8> ran,
                     ffi::ResultBuffer<ffi::S32> positions, ffi::ResultBuffer<ffi::S32> unsure,
                     ffi::ResultBuffer<ffi::S32> yes, ffi::ResultBuffer<ffi::S32> counts, int32_t flags,
                     int64_t n_roots) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  const int64_t P = h.n_pcols;
  PMX_CHECK(Expect("camera", camera.dimensions(), {PMX_CAMERA}));
  PMX_CHECK(Expect("unsure", unsure->dimensions(), {P + PMX_SPARE}));
  PMX_CHECK(Expect("yes", yes->dimensions(), {P + PMX_SPARE}));
  PMX_CHECK(Expect("counts", counts->dimensions(), {5}));
  auto lists = OneLists(P, pcols, ran, positions);
  if (lists.has_error()) return lists.error();
  Scratch s(P);
  if (!s.s) return Status(PMX_NO_MEMORY, "refine");
  float view[PMX_VIEW];
  pmx_view_of(camera.typed_data(), (flags & PMX_ORTHOGRAPHIC) != 0, view);
  PmxCounts c{};
  int level = 0;
  PMX_CHECK(Status(pmx_refine_one(&h, view, flags, -1, nullptr, nullptr, 0, lists.value(),
                                  unsure->typed_data(), &c, &level, s.s),
                   "refine"));
  PutCounts(c, level, counts->typed_data());
  return ffi::Error::Success();
}

// The second pass, where the first left unsure decisions: the same traversal
// at the same SIMD level, each unsure decision answered (yes[i] for the
// position unsure[i]); nothing to do where there were none.
// operands: rows, kills, order, camera, pcols, ran, positions (the first pass's lists), unsure, yes,
//           counts s32[5] (the first pass's)
// results: pcols, ran, positions (aliasing the operands), counts s32[5]
ffi::Error RefineAnswered(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills, ffi::Buffer<ffi::S32> order,
                          ffi::Buffer<ffi::F32> camera, ffi::Buffer<ffi::S32> pcols_in, ffi::Buffer<ffi::U8> ran_in,
                          ffi::Buffer<ffi::S32> positions_in, ffi::Buffer<ffi::S32> unsure, ffi::Buffer<ffi::S32> yes,
                          ffi::Buffer<ffi::S32> counts_in, ffi::ResultBuffer<ffi::S32> pcols,
                          ffi::ResultBuffer<ffi::U8> ran, ffi::ResultBuffer<ffi::S32> positions,
                          ffi::ResultBuffer<ffi::S32> counts, int32_t flags, int64_t n_roots) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  const int64_t P = h.n_pcols;
  PMX_CHECK(Expect("camera", camera.dimensions(), {PMX_CAMERA}));
  PMX_CHECK(Expect("unsure", unsure.dimensions(), {P + PMX_SPARE}));
  PMX_CHECK(Expect("yes", yes.dimensions(), {P + PMX_SPARE}));
  PMX_CHECK(Expect("counts", counts_in.dimensions(), {5}));
  PMX_CHECK(Expect("counts", counts->dimensions(), {5}));
  auto lists = OneLists(P, pcols, ran, positions);
  if (lists.has_error()) return lists.error();
  if (pcols_in.element_count() != pcols->element_count() || ran_in.element_count() != ran->element_count() ||
      positions_in.element_count() != positions->element_count())
    return ffi::Error::InvalidArgument("the lists must be the first pass's");
  const int32_t* first = counts_in.typed_data();
  const int64_t m = first[3];
  if (m < 0 || m > P) return ffi::Error::InvalidArgument("counts: the unsure decisions do not fit the hierarchy");
  if (m == 0) {  // the first pass was exact: its results stand
    if (pcols->typed_data() != pcols_in.typed_data())
      std::memcpy(pcols->typed_data(), pcols_in.typed_data(), pcols_in.size_bytes());
    if (ran->typed_data() != ran_in.typed_data())
      std::memcpy(ran->typed_data(), ran_in.typed_data(), ran_in.size_bytes());
    if (positions->typed_data() != positions_in.typed_data())
      std::memcpy(positions->typed_data(), positions_in.typed_data(), positions_in.size_bytes());
    std::memcpy(counts->typed_data(), first, 5 * sizeof(int32_t));
    return ffi::Error::Success();
  }
  Scratch s(P);
  if (!s.s) return Status(PMX_NO_MEMORY, "refine");
  float view[PMX_VIEW];
  pmx_view_of(camera.typed_data(), (flags & PMX_ORTHOGRAPHIC) != 0, view);
  PmxCounts c{};
  int level = 0;
  PMX_CHECK(Status(pmx_refine_one(&h, view, flags, static_cast<int>(first[4]), unsure.typed_data(),
                                  yes.typed_data(), m, lists.value(), nullptr, &c, &level, s.s),
                   "refine"));
  if (c.unsure != 0) return ffi::Error::Internal("refine: unsure decisions left after they were answered");
  PutCounts(c, level, counts->typed_data());
  return ffi::Error::Success();
}

// The records and pairs results of a batch: records s32[R], pairs s32[N, 4]
// (at, item, position, frames), sizes s32[2] (records used, pairs).
ffi::Error CheckRecords(ffi::Span<const int64_t> records, ffi::Span<const int64_t> pairs,
                        ffi::Span<const int64_t> sizes) {
  if (records.size() != 1 || records[0] < 2 || records[0] >= (int64_t(1) << 31))
    return ffi::Error::InvalidArgument("records must have shape [R], 2 <= R < 2^31, got " + Shape(records));
  PMX_CHECK(Expect("pairs", pairs, {records[0] / PMX_NODE + 1, 4}));
  PMX_CHECK(Expect("sizes", sizes, {2}));
  return ffi::Error::Success();
}

// The unsure pairs of the records used, into pairs [N, 4] (N = R / PMX_NODE + 1
// holds them all: a pair is a node of PMX_NODE int32); sizes = (used, pairs).
void Pairs(const int32_t* records, int64_t used, int32_t* pairs, int32_t* sizes) {
  std::vector<int64_t> at(used / PMX_NODE + 1);
  std::vector<int32_t> item(at.size()), position(at.size()), frames(at.size());
  const int64_t n = pmx_unsure_pairs(records, used, at.data(), item.data(), position.data(), frames.data());
  for (int64_t i = 0; i < n; ++i) {
    pairs[4 * i] = static_cast<int32_t>(at[i]);
    pairs[4 * i + 1] = item[i], pairs[4 * i + 2] = position[i], pairs[4 * i + 3] = frames[i];
  }
  sizes[0] = static_cast<int32_t>(used), sizes[1] = static_cast<int32_t>(n);
}

// ---- camera batches ----------------------------------------------------------
// operands: rows, kills, order, cameras f32[K, PMX_CAMERA]
// results: counts s32[K, 4], masks u8[K, P] or [0], pcols s32[K, L], ran u8[K, L], positions s32[K, L]
//          (L = P + PMX_SPARE, or shape [0]), records s32[R], pairs s32[N, 4], yes s32[N] (not written: room
//          for the caller's answers), sizes s32[2], overflow u8[K]
ffi::Error RefineMany(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills,
                      ffi::Buffer<ffi::S32> order, ffi::Buffer<ffi::F32> cameras, ffi::ResultBuffer<ffi::S32> counts,
                      ffi::ResultBuffer<ffi::U8> masks, ffi::ResultBuffer<ffi::S32> pcols,
                      ffi::ResultBuffer<ffi::U8> ran, ffi::ResultBuffer<ffi::S32> positions,
                      ffi::ResultBuffer<ffi::S32> records, ffi::ResultBuffer<ffi::S32> pairs,
                      ffi::ResultBuffer<ffi::S32> yes, ffi::ResultBuffer<ffi::S32> sizes,
                      ffi::ResultBuffer<ffi::U8> overflow, int32_t flags, int64_t n_roots, int64_t threads) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  const int64_t P = h.n_pcols;
  auto vd = cameras.dimensions();
  if (vd.size() != 2 || vd[1] != PMX_CAMERA)
    return ffi::Error::InvalidArgument("cameras must have shape [K, " + std::to_string(PMX_CAMERA) + "], got " +
                                       Shape(vd));
  const int64_t K = vd[0];
  std::vector<float> views(K * PMX_VIEW);
  pmx_views_of(cameras.typed_data(), K, (flags & PMX_ORTHOGRAPHIC) != 0, views.data());
  PMX_CHECK(Expect("counts", counts->dimensions(), {K, 4}));
  PMX_CHECK(Expect("overflow", overflow->dimensions(), {K}));
  const bool want_masks = masks->element_count() > 0;
  if (want_masks) PMX_CHECK(Expect("masks", masks->dimensions(), {K, P}));
  PmxLists lists{};
  for (auto [name, dims] : {std::pair{"pcols", pcols->dimensions()}, std::pair{"ran", ran->dimensions()},
                            std::pair{"positions", positions->dimensions()}}) {
    auto wanted = ListWanted(name, dims, K, P);
    if (wanted.has_error()) return wanted.error();
  }
  if (pcols->element_count()) lists.pcols = pcols->typed_data();
  if (ran->element_count()) lists.ran = ran->typed_data();
  if (positions->element_count()) lists.positions = positions->typed_data();
  PMX_CHECK(CheckRecords(records->dimensions(), pairs->dimensions(), sizes->dimensions()));
  PMX_CHECK(Expect("yes", yes->dimensions(), {pairs->dimensions()[0]}));
  PmxRecords rec{records->typed_data(), records->dimensions()[0], 0};
  static_assert(sizeof(PmxCounts) == 4 * sizeof(int32_t), "PmxCounts is four int32");
  PmxRunner runner = Runner(pool, threads);
  PMX_CHECK(Status(pmx_refine_many(&h, views.data(), K, flags, reinterpret_cast<PmxCounts*>(counts->typed_data()),
                                   want_masks ? masks->typed_data() : nullptr, lists, &rec, overflow->typed_data(),
                                   &runner),
                   "refine_batch"));
  Pairs(rec.records, rec.used, pairs->typed_data(), sizes->typed_data());
  return ffi::Error::Success();
}

// ---- face budgets of camera batches -----------------------------------------
// operands: rows, kills, order, cameras f32[K, PMX_CAMERA] (tau: a first tolerance, or 0), units f32[K]
//           (one pixel), budgets s32[K, B] (B budgets per camera)
// results: guess s32[K, B], guess_alt s32[K, B] (float32 bit patterns; 0x7F800001: inf; -1: a word's frame
//          left to its own traversal)
// words: 1 when the cameras are words of 16 frames of a path (K a multiple of 16)
ffi::Error BudgetMany(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills,
                      ffi::Buffer<ffi::S32> order, ffi::Buffer<ffi::F32> cameras, ffi::Buffer<ffi::F32> units,
                      ffi::Buffer<ffi::S32> budgets, ffi::ResultBuffer<ffi::S32> guess,
                      ffi::ResultBuffer<ffi::S32> guess_alt, int32_t flags, int64_t n_roots, int64_t base_faces,
                      int64_t threads, int32_t words) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  auto vd = cameras.dimensions();
  if (vd.size() != 2 || vd[1] != PMX_CAMERA)
    return ffi::Error::InvalidArgument("cameras must have shape [K, " + std::to_string(PMX_CAMERA) + "], got " +
                                       Shape(vd));
  const int64_t K = vd[0];
  PMX_CHECK(Expect("units", units.dimensions(), {K}));
  auto bd = budgets.dimensions();
  if (bd.size() != 2 || bd[0] != K || bd[1] < 1)
    return ffi::Error::InvalidArgument("budgets must have shape [" + std::to_string(K) + ", B] with B >= 1, got " +
                                       Shape(bd));
  const int64_t B = bd[1];
  PMX_CHECK(Expect("guess", guess->dimensions(), {K, B}));
  PMX_CHECK(Expect("guess_alt", guess_alt->dimensions(), {K, B}));
  if (base_faces < 0) return ffi::Error::InvalidArgument("base_faces must be >= 0");
  PmxRunner runner = Runner(pool, threads);
  PMX_CHECK(Status(pmx_budget_many(&h, cameras.typed_data(), units.typed_data(), K, flags, budgets.typed_data(), B,
                                   base_faces, guess->typed_data(), guess_alt->typed_data(), words, &runner),
                   "faces_for_budget"));
  return ffi::Error::Success();
}

// ---- words of a path ---------------------------------------------------------
// operands: rows, kills, order, cameras f32[W * 16, PMX_CAMERA]
// results: counts s32[W * 16, 4], at_once s32[W], pcols s32[W, L], ran u16[W, L], positions s32[W, L],
//          records s32[R], pairs s32[N, 4], yes s32[N] (room for the answers), sizes s32[2], overflow u8[W]
// sets > 1: the words in groups of `sets` (pmx_refine_word_sets), counts only (lists [W, 0]).
ffi::Error RefineWords(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills,
                       ffi::Buffer<ffi::S32> order, ffi::Buffer<ffi::F32> cameras, ffi::ResultBuffer<ffi::S32> counts,
                       ffi::ResultBuffer<ffi::S32> at_once, ffi::ResultBuffer<ffi::S32> pcols,
                       ffi::ResultBuffer<ffi::U16> ran, ffi::ResultBuffer<ffi::S32> positions,
                       ffi::ResultBuffer<ffi::S32> records, ffi::ResultBuffer<ffi::S32> pairs,
                       ffi::ResultBuffer<ffi::S32> yes, ffi::ResultBuffer<ffi::S32> sizes,
                       ffi::ResultBuffer<ffi::U8> overflow, int32_t flags, int64_t n_roots, int64_t threads,
                       int64_t sets) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  const int64_t P = h.n_pcols;
  auto vd = cameras.dimensions();
  if (vd.size() != 2 || vd[1] != PMX_CAMERA || vd[0] % PMX_FRAMES != 0)
    return ffi::Error::InvalidArgument("cameras must have shape [W * 16, " + std::to_string(PMX_CAMERA) + "], got " +
                                       Shape(vd));
  const int64_t W = vd[0] / PMX_FRAMES;
  std::vector<float> views(vd[0] * PMX_VIEW);
  pmx_views_of(cameras.typed_data(), vd[0], (flags & PMX_ORTHOGRAPHIC) != 0, views.data());
  PMX_CHECK(Expect("counts", counts->dimensions(), {W * PMX_FRAMES, 4}));
  PMX_CHECK(Expect("at_once", at_once->dimensions(), {W}));
  PMX_CHECK(Expect("overflow", overflow->dimensions(), {W}));
  PmxLists lists{};
  for (auto [name, dims] : {std::pair{"pcols", pcols->dimensions()}, std::pair{"ran", ran->dimensions()},
                            std::pair{"positions", positions->dimensions()}}) {
    auto wanted = ListWanted(name, dims, W, P);
    if (wanted.has_error()) return wanted.error();
  }
  if (pcols->element_count()) lists.pcols = pcols->typed_data();
  if (ran->element_count()) lists.ran_frames = ran->typed_data();
  if (positions->element_count()) lists.positions = positions->typed_data();
  PMX_CHECK(CheckRecords(records->dimensions(), pairs->dimensions(), sizes->dimensions()));
  PMX_CHECK(Expect("yes", yes->dimensions(), {pairs->dimensions()[0]}));
  PmxRecords rec{records->typed_data(), records->dimensions()[0], 0};
  PmxRunner runner = Runner(pool, threads);
  auto* out = reinterpret_cast<PmxCounts*>(counts->typed_data());
  if (sets == 1) {
    PMX_CHECK(Status(pmx_refine_words(&h, views.data(), W, flags, out, lists, at_once->typed_data(), &rec,
                                      overflow->typed_data(), &runner),
                     "path"));
  } else {
    // Words in sets of the same frames at several tolerances: counts only.
    if (sets < 1 || sets > PMX_MOST_SETS || W % sets != 0)
      return ffi::Error::InvalidArgument("sets must be 1 to " + std::to_string(PMX_MOST_SETS) +
                                         " and divide the words (" + std::to_string(W) +
                                         "), got " + std::to_string(sets));
    if (lists.pcols || lists.ran_frames || lists.positions)
      return ffi::Error::InvalidArgument("word sets have no lists");
    PMX_CHECK(Status(pmx_refine_word_sets(&h, views.data(), W, static_cast<int>(sets), flags, out,
                                          at_once->typed_data(), &rec, overflow->typed_data(), &runner),
                     "path"));
  }
  Pairs(rec.records, rec.used, pairs->typed_data(), sizes->typed_data());
  return ffi::Error::Success();
}

// ---- unsure pairs decided: counts, masks and lists corrected -----------------
// operands: records s32[R], sizes s32[2], pairs s32[N, 4], yes s32[N], counts s32[M, 4],
//           masks u8[K, P] or [0], ran (u8[K, L] for cameras, u16[W, L] for words, or [0]), order s32[P]
// results: records, counts, masks, ran (each aliasing its operand)
ffi::Error ApplyUnsure(ffi::Buffer<ffi::S32> records_in, ffi::Buffer<ffi::S32> sizes, ffi::Buffer<ffi::S32> pairs,
                       ffi::Buffer<ffi::S32> yes, ffi::Buffer<ffi::S32> counts_in, ffi::Buffer<ffi::U8> masks_in,
                       ffi::AnyBuffer ran_in, ffi::Buffer<ffi::S32> order, ffi::ResultBuffer<ffi::S32> records,
                       ffi::ResultBuffer<ffi::S32> counts, ffi::ResultBuffer<ffi::U8> masks,
                       ffi::Result<ffi::AnyBuffer> ran, int32_t frames) {
  PMX_CHECK(CheckRecords(records_in.dimensions(), pairs.dimensions(), sizes.dimensions()));
  const int64_t R = records_in.dimensions()[0], N = pairs.dimensions()[0];
  PMX_CHECK(Expect("yes", yes.dimensions(), {N}));
  if (frames != 1 && frames != PMX_FRAMES) return ffi::Error::InvalidArgument("frames must be 1 or 16");
  const int64_t P = order.element_count();
  auto cd = counts_in.dimensions();
  if (cd.size() != 2 || cd[1] != 4 || cd[0] % frames != 0)
    return ffi::Error::InvalidArgument("counts must have shape [M, 4], got " + Shape(cd));
  const int64_t items = cd[0] / frames;
  if (masks_in.element_count()) PMX_CHECK(Expect("masks", masks_in.dimensions(), {items, P}));
  if (frames == PMX_FRAMES && masks_in.element_count())
    return ffi::Error::InvalidArgument("words have no masks");
  PmxLists lists{};
  if (ran_in.element_count()) {
    PMX_CHECK(Expect("ran", ran_in.dimensions(), {items, P + PMX_SPARE}));
    const bool words = frames == PMX_FRAMES;
    if (ran_in.element_type() != (words ? ffi::DataType::U16 : ffi::DataType::U8))
      return ffi::Error::InvalidArgument(words ? "ran must be uint16 for words" : "ran must be uint8 for cameras");
    if (words)
      lists.ran_frames = reinterpret_cast<uint16_t*>(ran->untyped_data());
    else
      lists.ran = reinterpret_cast<uint8_t*>(ran->untyped_data());
  }
  // Results alias their operands; copy where XLA gave a separate buffer.
  if (records->typed_data() != records_in.typed_data())
    std::memcpy(records->typed_data(), records_in.typed_data(), sizeof(int32_t) * R);
  if (counts->typed_data() != counts_in.typed_data())
    std::memcpy(counts->typed_data(), counts_in.typed_data(), counts_in.size_bytes());
  if (masks_in.element_count() && masks->typed_data() != masks_in.typed_data())
    std::memcpy(masks->typed_data(), masks_in.typed_data(), masks_in.size_bytes());
  if (ran_in.element_count() && ran->untyped_data() != ran_in.untyped_data())
    std::memcpy(ran->untyped_data(), ran_in.untyped_data(), ran_in.size_bytes());
  const int64_t used = sizes.typed_data()[0], n = sizes.typed_data()[1];
  if (used < 0 || used > R || n < 0 || n > N) return ffi::Error::InvalidArgument("sizes do not fit the records");
  const int32_t* p = pairs.typed_data();
  std::vector<int64_t> at(n);
  for (int64_t i = 0; i < n; ++i) {
    at[i] = p[4 * i];
    if (at[i] < 0 || at[i] >= used) return ffi::Error::InvalidArgument("pairs do not fit the records");
  }
  pmx_apply_unsure(records->typed_data(), used, at.data(), yes.typed_data(), n, frames,
                   reinterpret_cast<PmxCounts*>(counts->typed_data()), order.typed_data(), P,
                   masks_in.element_count() ? masks->typed_data() : nullptr, lists);
  return ffi::Error::Success();
}

// ---- the mesh --------------------------------------------------------------------
// The front mesh's operands as plain arrays (the XLA target's buffers, or
// the eager entry's NumPy arrays): data and shape of each.
template <typename T>
struct Raw {
  T* data;
  ffi::Span<const int64_t> dims;
};

struct MeshOperands {
  Raw<const int32_t> pcol_records, kill_data, base, tops, top_at;
  Raw<const void> ran;
  bool words;  // ran: uint16 frame bits of words (else uint8 per camera)
  Raw<const int32_t> positions, counts;
  int64_t item;
  Raw<int32_t> faces, ids;
  Raw<float> vertex_positions;
  int64_t n_original, n_faces_total;
};

// Checks the operands against each other and reads the mesh off the front:
// faces, ids and vertex_positions written, *n_ids their vertices.
ffi::Error FrontMeshOf(const MeshOperands& a, int64_t* n_ids) {
  static_assert(sizeof(PmxPcolRecord) == 14 * 4 && sizeof(PmxFaceRecord) == 16 && sizeof(PmxFrontVertex) == 20,
                "records of 4-byte fields");
  auto pd = a.pcol_records.dims;
  if (pd.size() != 2 || pd[1] != 14)
    return ffi::Error::InvalidArgument("pcol_records must have shape [P, 14], got " + Shape(pd));
  const int64_t P = pd[0], V0 = a.n_original, F = a.n_faces_total;
  auto kd = a.kill_data.dims, bd = a.base.dims, td = a.tops.dims;
  if (kd.size() != 2 || kd[1] != 4) return ffi::Error::InvalidArgument("kill_data must have shape [n, 4]");
  if (bd.size() != 2 || bd[1] != 4) return ffi::Error::InvalidArgument("base must have shape [n, 4]");
  if (td.size() != 2 || td[1] != 5) return ffi::Error::InvalidArgument("tops must have shape [n, 5]");
  PMX_CHECK(Expect("top_at", a.top_at.dims, {td[0]}));
  if (V0 < 0 || F < 0 || kd[0] + bd[0] > F)
    return ffi::Error::InvalidArgument("the mesh's records do not fit its faces");
  // A face's corners are numbered 3 * face + c in int32.
  if (F > INT32_MAX / 3)
    return ffi::Error::InvalidArgument("the mesh's " + std::to_string(F) + " faces are more than " +
                                       std::to_string(INT32_MAX / 3));
  // The outputs' rows: room for the refinement's faces (checked below) and
  // for the vertices it uses (the core checks), at most the whole mesh.
  auto fd = a.faces.dims, id = a.ids.dims;
  if (fd.size() != 2 || fd[1] != 3 || fd[0] > F)
    return ffi::Error::InvalidArgument("faces must have shape [rows <= " + std::to_string(F) + ", 3], got " +
                                       Shape(fd));
  if (id.size() != 1 || id[0] > V0)
    return ffi::Error::InvalidArgument("ids must have shape [rows <= " + std::to_string(V0) + "], got " + Shape(id));
  PMX_CHECK(Expect("vertex_positions", a.vertex_positions.dims, {id[0], 3}));
  auto rd = a.ran.dims, qd = a.positions.dims, cd = a.counts.dims;
  if (rd.size() != qd.size() || !std::equal(rd.begin(), rd.end(), qd.begin()) || rd.size() < 1 || rd.size() > 2)
    return ffi::Error::InvalidArgument("ran and positions must have the same shape, [L] or [R, L]; got " +
                                       Shape(rd) + " and " + Shape(qd));
  if (cd.size() < 1 || cd.size() > 2 || cd.back() < 4)
    return ffi::Error::InvalidArgument("counts must be [C] or [M, C] with C >= 4, got " + Shape(cd));
  const int64_t item = a.item, items = cd.size() == 2 ? cd[0] : 1;
  const int64_t rows = rd.size() == 2 ? rd[0] : 1, L = rd.back();
  const int64_t row = a.words ? item / PMX_FRAMES : item;
  if (item < 0 || item >= items || row >= rows) return ffi::Error::InvalidArgument("item outside the counts or lists");
  const int32_t* c = a.counts.data + cd.back() * item;
  const int64_t n = c[0], nf = bd[0] + c[2];
  if (n < 0 || n > L || n > P)
    return ffi::Error::InvalidArgument("counts: the " + std::to_string(n) + " slots do not fit the lists of " +
                                       std::to_string(L) + " slots and " + std::to_string(P) + " pcols");
  if (nf < 0 || nf > fd[0])
    return ffi::Error::InvalidArgument("counts: the refinement's " + std::to_string(nf) + " faces do not fit " +
                                       std::to_string(fd[0]) + " rows");
  const uint8_t* ran8 = a.words ? nullptr : static_cast<const uint8_t*>(a.ran.data) + row * L;
  const uint16_t* ran16 = a.words ? static_cast<const uint16_t*>(a.ran.data) + row * L : nullptr;
  const int frame = a.words ? static_cast<int>(item % PMX_FRAMES) : -1;
  const int32_t* at = a.positions.data + row * L;
  for (int64_t i = 0; i < n; ++i)
    if (at[i] < 0 || at[i] >= P)
      return ffi::Error::InvalidArgument("positions[" + std::to_string(i) + "] = " + std::to_string(at[i]) +
                                         " is outside the hierarchy's " + std::to_string(P) + " positions");
  PmxMeshTables m{reinterpret_cast<const PmxPcolRecord*>(a.pcol_records.data),
                  reinterpret_cast<const PmxFaceRecord*>(a.kill_data.data),
                  reinterpret_cast<const PmxFaceRecord*>(a.base.data),
                  reinterpret_cast<const PmxFrontVertex*>(a.tops.data),
                  a.top_at.data,
                  kd[0],
                  bd[0],
                  td[0],
                  V0,
                  P,
                  F};
  Scratch s(P);
  if (!s.s) return Status(PMX_NO_MEMORY, "mesh");
  const PmxStatus status = pmx_front_mesh(&m, ran8, ran16, frame, at, n, nf, a.faces.data, a.ids.data,
                                          a.vertex_positions.data, id[0], n_ids, s.s);
  // A record that points outside the tables, named with its index.
  static const char* tables[] = {"pcol_records", "kill_data", "base", "tops"};
  if (status >= PMX_BAD_PCOL_RECORD && status <= PMX_BAD_TOP_RECORD)
    return ffi::Error::InvalidArgument(std::string("mesh: ") + tables[status - PMX_BAD_PCOL_RECORD] + "[" +
                                       std::to_string(*n_ids) + "]: " + pmx_status_text(status));
  return Status(status, "mesh");
}

template <ffi::DataType T>
auto In(const ffi::Buffer<T>& b) {
  return Raw<const ffi::NativeType<T>>{b.typed_data(), b.dimensions()};
}

template <ffi::DataType T>
auto Out(ffi::Result<ffi::Buffer<T>>& b) {
  return Raw<ffi::NativeType<T>>{b->typed_data(), b->dimensions()};
}

// The refined mesh read off the front (FrontMeshOf).
// operands: pcol_records s32[P, 14], kill_data s32[KD, 4], base s32[B, 4], tops s32[T, 5], top_at s32[T],
//           ran (u8 [L] or [R, L]; or a path's u16 frame bits [R, L]) and positions s32 of the same shape,
//           counts s32[C] or [M, C] (slots visited, not run, kept, ...: a refinement's counts), item s32[]:
//           the refinement's row of counts; its lists are row item / 16 of words' (u16), item of cameras'
//           (u8 [R, L]), and the frame bit item % 16.
// results: faces s32[rows <= F, 3], ids s32[n <= V0], vertex_positions f32[n, 3], n_ids s32[]
ffi::Error FrontMesh(ffi::Buffer<ffi::S32> pcol_records, ffi::Buffer<ffi::S32> kill_data,
                     ffi::Buffer<ffi::S32> base, ffi::Buffer<ffi::S32> tops, ffi::Buffer<ffi::S32> top_at,
                     ffi::AnyBuffer ran, ffi::Buffer<ffi::S32> positions, ffi::Buffer<ffi::S32> counts,
                     ffi::Buffer<ffi::S32> item_of, ffi::ResultBuffer<ffi::S32> faces, ffi::ResultBuffer<ffi::S32> ids,
                     ffi::ResultBuffer<ffi::F32> vertex_positions, ffi::ResultBuffer<ffi::S32> n_ids,
                     int64_t n_original, int64_t n_faces_total) {
  const bool words = ran.element_type() == ffi::DataType::U16;
  if (!words && ran.element_type() != ffi::DataType::U8 && ran.element_type() != ffi::DataType::PRED)
    return ffi::Error::InvalidArgument("ran must be uint8 (cameras) or uint16 (words' frames)");
  MeshOperands a{In(pcol_records), In(kill_data), In(base), In(tops), In(top_at),
                 Raw<const void>{ran.untyped_data(), ran.dimensions()}, words, In(positions), In(counts),
                 item_of.typed_data()[0], Out(faces), Out(ids), Out(vertex_positions), n_original, n_faces_total};
  int64_t count = 0;
  PMX_CHECK(FrontMeshOf(a, &count));
  n_ids->typed_data()[0] = static_cast<int32_t>(count);
  return ffi::Error::Success();
}

// ---- checks and the tests' whole-table passes ----------------------------------
// operands: rows, kills, order; results: status s32[] (0)
ffi::Error CheckHierarchy(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::S32> kills, ffi::Buffer<ffi::S32> order,
                          ffi::ResultBuffer<ffi::S32> status, int64_t n_roots) {
  PmxHierarchy h;
  PMX_CHECK(Hierarchy(rows, kills, order, n_roots, &h));
  PMX_CHECK(Status(pmx_check_hierarchy(&h), "hierarchy"));
  status->typed_data()[0] = 0;
  return ffi::Error::Success();
}

// operands: cameras f32[K, PMX_CAMERA]; results: views f32[K, 22]
ffi::Error Views(ffi::Buffer<ffi::F32> cameras, ffi::ResultBuffer<ffi::F32> views, int32_t orthographic) {
  auto dims = cameras.dimensions();
  if (dims.size() != 2 || dims[1] != PMX_CAMERA)
    return ffi::Error::InvalidArgument("cameras must have shape [K, " + std::to_string(PMX_CAMERA) + "], got " +
                                       Shape(dims));
  PMX_CHECK(Expect("views", views->dimensions(), {dims[0], PMX_VIEW}));
  pmx_views_of(cameras.typed_data(), dims[0], orthographic != 0, views->typed_data());
  return ffi::Error::Success();
}

// operands: rows f32[P, 16], view f32[22]; results: out u8[P]
ffi::Error DecideAll(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::F32> view, ffi::ResultBuffer<ffi::U8> out,
                     int32_t flags) {
  auto dims = rows.dimensions();
  if (dims.size() != 2 || dims[1] != PMX_ROW) return ffi::Error::InvalidArgument("rows must have shape [P, 16]");
  PMX_CHECK(Expect("view", view.dimensions(), {PMX_VIEW}));
  PMX_CHECK(Expect("out", out->dimensions(), {dims[0]}));
  pmx_decide_all(rows.typed_data(), dims[0], view.typed_data(), flags, out->typed_data());
  return ffi::Error::Success();
}

// operands: views f32[W, F, 22]; results: out f32[W, 29]
ffi::Error FatCameras(ffi::Buffer<ffi::F32> views, ffi::ResultBuffer<ffi::F32> out) {
  auto dims = views.dimensions();
  if (dims.size() != 3 || dims[2] != PMX_VIEW || dims[1] < 1 || dims[1] > 64)
    return ffi::Error::InvalidArgument("views must have shape [W, F, 22] with 1 <= F <= 64, got " + Shape(dims));
  PMX_CHECK(Expect("out", out->dimensions(), {dims[0], PMX_FAT}));
  return Status(pmx_fat_cameras(views.typed_data(), dims[0], static_cast<int>(dims[1]), out->typed_data()),
                "fat cameras");
}

// operands: rows f32[P, 16], views f32[F, 22], fat f32[29]; results: out u8[P]
ffi::Error DecideFatAll(ffi::Buffer<ffi::F32> rows, ffi::Buffer<ffi::F32> views, ffi::Buffer<ffi::F32> fat,
                        ffi::ResultBuffer<ffi::U8> out, int32_t flags) {
  auto dims = rows.dimensions(), vd = views.dimensions();
  if (dims.size() != 2 || dims[1] != PMX_ROW) return ffi::Error::InvalidArgument("rows must have shape [P, 16]");
  if (vd.size() != 2 || vd[1] != PMX_VIEW || vd[0] < 1 || vd[0] > PMX_FRAMES)
    return ffi::Error::InvalidArgument("views must have shape [F, 22] with 1 <= F <= 16, got " + Shape(vd));
  PMX_CHECK(Expect("fat", fat.dimensions(), {PMX_FAT}));
  PMX_CHECK(Expect("out", out->dimensions(), {dims[0]}));
  pmx_decide_fat_all(rows.typed_data(), dims[0], views.typed_data(), static_cast<int>(vd[0]), flags,
                     fat.typed_data(), out->typed_data());
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxRefineOne, RefineOne,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<int32_t>("flags")
                                  .Attr<int64_t>("n_roots"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxRefineAnswered, RefineAnswered,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::U8>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<int32_t>("flags")
                                  .Attr<int64_t>("n_roots"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxRefineMany, RefineMany,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Attr<int32_t>("flags")
                                  .Attr<int64_t>("n_roots")
                                  .Attr<int64_t>("threads"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxBudgetMany, BudgetMany,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<int32_t>("flags")
                                  .Attr<int64_t>("n_roots")
                                  .Attr<int64_t>("base_faces")
                                  .Attr<int64_t>("threads")
                                  .Attr<int32_t>("words"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxRefineWords, RefineWords,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U16>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Attr<int32_t>("flags")
                                  .Attr<int64_t>("n_roots")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("sets"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxApplyUnsure, ApplyUnsure,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::U8>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Attr<int32_t>("frames"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxFrontMesh, FrontMesh,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("n_original")
                                  .Attr<int64_t>("n_faces_total"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxCheckHierarchy, CheckHierarchy,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("n_roots"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxViews, Views,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int32_t>("orthographic"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxDecideAll, DecideAll,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Attr<int32_t>("flags"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxFatCameras, FatCameras,
                              ffi::Ffi::Bind().Arg<ffi::Buffer<ffi::F32>>().Ret<ffi::Buffer<ffi::F32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(PmxDecideFatAll, DecideFatAll,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::U8>>()
                                  .Attr<int32_t>("flags"));

// ---- the Python module ------------------------------------------------------------

namespace {

PyObject* Targets(PyObject*, PyObject*) {
  struct {
    const char* name;
    void* fn;
  } targets[] = {{"pmx_refine_one", reinterpret_cast<void*>(PmxRefineOne)},
                 {"pmx_refine_answered", reinterpret_cast<void*>(PmxRefineAnswered)},
                 {"pmx_refine_many", reinterpret_cast<void*>(PmxRefineMany)},
                 {"pmx_refine_words", reinterpret_cast<void*>(PmxRefineWords)},
                 {"pmx_budget_many", reinterpret_cast<void*>(PmxBudgetMany)},
                 {"pmx_apply_unsure", reinterpret_cast<void*>(PmxApplyUnsure)},
                 {"pmx_front_mesh", reinterpret_cast<void*>(PmxFrontMesh)},
                 {"pmx_check_hierarchy", reinterpret_cast<void*>(PmxCheckHierarchy)},
                 {"pmx_views", reinterpret_cast<void*>(PmxViews)},
                 {"pmx_decide_all", reinterpret_cast<void*>(PmxDecideAll)},
                 {"pmx_fat_cameras", reinterpret_cast<void*>(PmxFatCameras)},
                 {"pmx_decide_fat_all", reinterpret_cast<void*>(PmxDecideFatAll)}};
  PyObject* out = PyDict_New();
  if (!out) return nullptr;
  for (auto& t : targets) {
    PyObject* capsule = PyCapsule_New(t.fn, nullptr, nullptr);
    if (!capsule || PyDict_SetItemString(out, t.name, capsule) < 0) {
      Py_XDECREF(capsule);
      Py_DECREF(out);
      return nullptr;
    }
    Py_DECREF(capsule);
  }
  return out;
}

PyObject* Simd(PyObject*, PyObject* args) {
  int level = -1;
  if (!PyArg_ParseTuple(args, "|i", &level)) return nullptr;
  return PyLong_FromLong(pmx_simd(level));
}

PyObject* MeshRanks(PyObject*, PyObject* args) {
  int mode = -1;
  if (!PyArg_ParseTuple(args, "|i", &mode)) return nullptr;
  if (mode > 2) {
    PyErr_Format(PyExc_ValueError, "mesh_ranks: mode %d is not -1, 0, 1 or 2", mode);
    return nullptr;
  }
  return PyLong_FromLong(pmx_mesh_ranks(mode));
}

PyObject* SimdBest(PyObject*, PyObject*) { return PyLong_FromLong(pmx_simd_best()); }

PyObject* Layout(PyObject*, PyObject*) {
  return Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i}", "row", PMX_ROW, "view", PMX_VIEW, "camera",
                       PMX_CAMERA, "frames", PMX_FRAMES, "fat", PMX_FAT, "node", PMX_NODE, "spare", PMX_SPARE,
                       "most_sets", PMX_MOST_SETS, "max_pcols", PMX_MAX_PCOLS,
                       "pcol_record", int(sizeof(PmxPcolRecord) / 4), "face_record", int(sizeof(PmxFaceRecord) / 4),
                       "front_vertex", int(sizeof(PmxFrontVertex) / 4));
}

PyObject* Drain(PyObject*, PyObject*) {
  pmx_scratch_drain();
  Py_RETURN_NONE;
}

// ---- eager single cameras ---------------------------------------------------
// An eager call of one camera reaches the core from Python directly (no XLA
// program around it), with the checks of the XLA targets: every array is
// read through the buffer protocol, C-contiguous, of the element type and
// shape the core expects; a mismatch is a ValueError naming the argument.

// An array (a NumPy array or any object with the buffer protocol) as an
// argument of the eager entry; None where the argument may be left out.
struct HostArray {
  Py_buffer view{};
  bool held = false;
  std::vector<int64_t> dims;
  HostArray() = default;
  HostArray(const HostArray&) = delete;
  HostArray& operator=(const HostArray&) = delete;
  ~HostArray() {
    if (held) PyBuffer_Release(&view);
  }
  template <typename T>
  T* data() const {
    return held ? static_cast<T*>(view.buf) : nullptr;
  }
  ffi::Span<const int64_t> shape() const { return ffi::Span<const int64_t>(dims.data(), dims.size()); }
};

// The element kind of a buffer-protocol format: 'f' float, 'i' signed, 'u'
// unsigned, 0 for anything else (byte orders other than the native one too).
char FormatKind(const char* format) {
  if (!format) return 'u';  // plain bytes
  if (*format == '@' || *format == '=' || *format == '<') ++format;
  if (!*format || format[1]) return 0;
  switch (*format) {
    case 'e': case 'f': case 'd': return 'f';
    case 'b': case 'h': case 'i': case 'l': case 'q': return 'i';
    case '?': case 'B': case 'H': case 'I': case 'L': case 'Q': return 'u';
    default: return 0;
  }
}

const char* KindName(char kind, Py_ssize_t size) {
  if (kind == 'u' && size == 0) return "uint8 or uint16";
  if (kind == 'f' && size == 4) return "float32";
  if (kind == 'i' && size == 4) return "int32";
  if (kind == 'u' && size == 1) return "uint8";
  return "an array";
}

// Takes `obj` as `a`: false, with a ValueError naming `name`, unless it is a
// C-contiguous array of `kind` and `size`-byte elements (size 0: unsigned of
// 1 or 2 bytes; writable for an output). None is taken as absent where `optional`.
bool Take(PyObject* obj, const char* name, char kind, Py_ssize_t size, bool writable, bool optional,
          HostArray* a) {
  if (obj == Py_None && optional) return true;
  int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
  if (obj == Py_None || PyObject_GetBuffer(obj, &a->view, flags) < 0) {
    PyErr_Clear();
    PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous%s %s array", name, writable ? ", writable" : "",
                 KindName(kind, size));
    return false;
  }
  a->held = true;
  bool sized = size ? a->view.itemsize == size : a->view.itemsize == 1 || a->view.itemsize == 2;
  if (FormatKind(a->view.format) != kind || !sized) {
    PyErr_Format(PyExc_ValueError, "%s must be %s, got elements of format '%s' and %zd bytes", name,
                 KindName(kind, size), a->view.format ? a->view.format : "B", a->view.itemsize);
    return false;
  }
  a->dims.assign(a->view.shape, a->view.shape + a->view.ndim);
  return true;
}

// An ffi::Error as a ValueError (false), or true.
bool Raise(const ffi::Error& error) {
  if (error.success()) return true;
  PyErr_SetString(PyExc_ValueError, error.message().c_str());
  return false;
}

// The hierarchy's tables rows f32[P, ROW], kills s32, order s32[P] taken
// (held by the caller's HostArrays) as a PmxHierarchy: false, with a
// ValueError naming the argument, unless they are one hierarchy's.
bool TakeHierarchy(PyObject* rows_o, PyObject* kills_o, PyObject* order_o, long long n_roots, HostArray* rows,
                   HostArray* kills, HostArray* order, PmxHierarchy* h) {
  return Take(rows_o, "rows", 'f', 4, false, false, rows) && Take(kills_o, "kills", 'i', 4, false, false, kills) &&
         Take(order_o, "order", 'i', 4, false, false, order) &&
         Raise(HierarchyOf(rows->data<float>(), rows->shape(), kills->data<int32_t>(), kills->shape(),
                           order->data<int32_t>(), order->shape(), n_roots, h));
}

// refine_one(rows, kills, order, camera, flags, n_roots, pcols, ran, positions, counts,
//            unsure=None, answered=None, answers=None, level=-1)
// One camera eagerly, as the XLA targets pmx_refine_one (answered None) and
// pmx_refine_answered (answered: the first pass's unsure positions, answers:
// the float32 predicate's decisions, level: the first pass's) compute it.
// Lists: pcols s32[L], ran u8[L], positions s32[L] (L = P + PMX_SPARE) or
// None (counts only); unsure s32[P + PMX_SPARE] or None; counts s32[5]
// (visited, not run, kept, unsure, SIMD level) written.
PyObject* RefineOneEager(PyObject*, PyObject* args, PyObject* kwargs) {
  static const char* names[] = {"rows", "kills", "order", "camera", "flags", "n_roots", "pcols", "ran",
                                "positions", "counts", "unsure", "answered", "answers", "level", nullptr};
  PyObject *rows_o, *kills_o, *order_o, *camera_o, *pcols_o, *ran_o, *positions_o, *counts_o;
  PyObject *unsure_o = Py_None, *answered_o = Py_None, *answers_o = Py_None;
  int flags = 0, level = -1;
  long long n_roots = 0;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OOOOiLOOOO|OOOi", const_cast<char**>(names), &rows_o, &kills_o,
                                   &order_o, &camera_o, &flags, &n_roots, &pcols_o, &ran_o, &positions_o, &counts_o,
                                   &unsure_o, &answered_o, &answers_o, &level))
    return nullptr;
  HostArray rows, kills, order, camera, pcols, ran, positions, counts, unsure, answered, answers;
  PmxHierarchy h;
  if (!TakeHierarchy(rows_o, kills_o, order_o, n_roots, &rows, &kills, &order, &h) ||
      !Take(camera_o, "camera", 'f', 4, false, false, &camera) ||
      !Take(pcols_o, "pcols", 'i', 4, true, true, &pcols) || !Take(ran_o, "ran", 'u', 1, true, true, &ran) ||
      !Take(positions_o, "positions", 'i', 4, true, true, &positions) ||
      !Take(counts_o, "counts", 'i', 4, true, false, &counts) ||
      !Take(unsure_o, "unsure", 'i', 4, true, true, &unsure) ||
      !Take(answered_o, "answered", 'i', 4, false, true, &answered) ||
      !Take(answers_o, "answers", 'i', 4, false, true, &answers))
    return nullptr;
  const int64_t P = h.n_pcols;
  if (!Raise(Expect("camera", camera.shape(), {PMX_CAMERA})) || !Raise(Expect("counts", counts.shape(), {5})))
    return nullptr;
  for (auto [name, list] : {std::pair{"pcols", &pcols}, std::pair{"ran", &ran}, std::pair{"positions", &positions},
                            std::pair{"unsure", &unsure}})
    if (list->held && !Raise(Expect(name, list->shape(), {P + PMX_SPARE}))) return nullptr;
  if (level < -1 || level > PMX_SIMD_AVX512) {
    PyErr_Format(PyExc_ValueError, "level must be -1 or a SIMD level 0..%d, got %d", PMX_SIMD_AVX512, level);
    return nullptr;
  }
  // The answers: both or neither, one per unsure position, the positions
  // increasing inside the hierarchy (the traversal merges them in order).
  if (answered.held != answers.held) {
    PyErr_SetString(PyExc_ValueError, "answered and answers go together");
    return nullptr;
  }
  int64_t m = 0;
  if (answered.held) {
    if (answered.dims.size() != 1 || answered.dims[0] > P + PMX_SPARE) {
      PyErr_Format(PyExc_ValueError, "answered must have shape [m], m <= %lld, got %s", (long long)(P + PMX_SPARE),
                   Shape(answered.shape()).c_str());
      return nullptr;
    }
    m = answered.dims[0];
    if (!Raise(Expect("answers", answers.shape(), {m}))) return nullptr;
    const int32_t* at = answered.data<int32_t>();
    for (int64_t i = 0; i < m; ++i)
      if (at[i] < 0 || at[i] >= P || (i > 0 && at[i] <= at[i - 1])) {
        PyErr_Format(PyExc_ValueError, "answered[%lld] = %d: the positions must increase inside [0, %lld)",
                     (long long)i, at[i], (long long)P);
        return nullptr;
      }
  }
  PmxLists lists{pcols.data<int32_t>(), ran.data<uint8_t>(), nullptr, positions.data<int32_t>()};
  float view[PMX_VIEW];
  pmx_view_of(camera.data<float>(), (flags & PMX_ORTHOGRAPHIC) != 0, view);
  PmxCounts c{};
  int level_used = 0;
  PmxStatus status = PMX_NO_MEMORY;
  Py_BEGIN_ALLOW_THREADS;
  if (PmxScratch* s = pmx_scratch_take(P)) {
    status = pmx_refine_one(&h, view, flags, level, answered.data<int32_t>(), answers.data<int32_t>(), m, lists,
                            unsure.data<int32_t>(), &c, &level_used, s);
    pmx_scratch_give(s);
  }
  Py_END_ALLOW_THREADS;
  if (status != PMX_OK) {
    PyErr_Format(status == PMX_NO_MEMORY ? PyExc_MemoryError : PyExc_ValueError, "refine: %s",
                 pmx_status_text(status));
    return nullptr;
  }
  PutCounts(c, level_used, counts.data<int32_t>());
  Py_RETURN_NONE;
}

template <typename T>
Raw<T> RawOf(const HostArray& a) {
  return Raw<T>{a.data<T>(), a.shape()};
}

// front_mesh(pcol_records, kill_data, base, tops, top_at, ran, positions, counts, item, n_original,
//            n_faces_total, faces, ids, vertex_positions) -> n_ids
// The mesh of one refinement eagerly, as the target pmx_front_mesh reads it
// (ran: uint8 per camera or uint16 frame bits of words); the outputs written.
PyObject* FrontMeshEager(PyObject*, PyObject* args) {
  PyObject *records_o, *kill_o, *base_o, *tops_o, *top_at_o, *ran_o, *positions_o, *counts_o, *faces_o, *ids_o,
      *vertices_o;
  long long item = 0, n_original = 0, n_faces_total = 0;
  if (!PyArg_ParseTuple(args, "OOOOOOOOLLLOOO", &records_o, &kill_o, &base_o, &tops_o, &top_at_o, &ran_o,
                        &positions_o, &counts_o, &item, &n_original, &n_faces_total, &faces_o, &ids_o, &vertices_o))
    return nullptr;
  HostArray records, kill_data, base, tops, top_at, ran, positions, counts, faces, ids, vertices;
  if (!Take(records_o, "pcol_records", 'i', 4, false, false, &records) ||
      !Take(kill_o, "kill_data", 'i', 4, false, false, &kill_data) ||
      !Take(base_o, "base", 'i', 4, false, false, &base) || !Take(tops_o, "tops", 'i', 4, false, false, &tops) ||
      !Take(top_at_o, "top_at", 'i', 4, false, false, &top_at) || !Take(ran_o, "ran", 'u', 0, false, false, &ran) ||
      !Take(positions_o, "positions", 'i', 4, false, false, &positions) ||
      !Take(counts_o, "counts", 'i', 4, false, false, &counts) ||
      !Take(faces_o, "faces", 'i', 4, true, false, &faces) || !Take(ids_o, "ids", 'i', 4, true, false, &ids) ||
      !Take(vertices_o, "vertex_positions", 'f', 4, true, false, &vertices))
    return nullptr;
  MeshOperands a{RawOf<const int32_t>(records), RawOf<const int32_t>(kill_data), RawOf<const int32_t>(base),
                 RawOf<const int32_t>(tops), RawOf<const int32_t>(top_at), RawOf<const void>(ran),
                 ran.view.itemsize == 2, RawOf<const int32_t>(positions), RawOf<const int32_t>(counts), item,
                 RawOf<int32_t>(faces), RawOf<int32_t>(ids), RawOf<float>(vertices), n_original, n_faces_total};
  int64_t n_ids = 0;
  ffi::Error error = ffi::Error::Success();
  Py_BEGIN_ALLOW_THREADS;
  error = FrontMeshOf(a, &n_ids);
  Py_END_ALLOW_THREADS;
  if (!Raise(error)) return nullptr;
  return PyLong_FromLongLong(n_ids);
}

// -- drawable front meshes along a path (mesh_stream.c) --------------------------------

// A stream and the tables it reads (their buffers held as long as it lives).
struct StreamHandle {
  PmxMeshStream* stream = nullptr;
  HostArray tables[10];
  int64_t n_pcols = 0;
  ~StreamHandle() { pmx_mesh_stream_free(stream); }
};

const char* kStreamCapsule = "pmjax.mesh_stream";

void FreeStream(PyObject* capsule) {
  delete static_cast<StreamHandle*>(PyCapsule_GetPointer(capsule, kStreamCapsule));
}

// mesh_stream_new(pcol_records, kill_data, base, tops, top_at, own_vertex, own_end, own_position, up,
//                 corners, n_original, n_faces) -> stream (a capsule)
// A stream at the fully collapsed mesh; the tables as front_mesh's, and per
// position the pcol's own vertex, the end of its depth-first interval and
// its position, the consuming positions (up) and the faces' original corners.
PyObject* MeshStreamNew(PyObject*, PyObject* args) {
  PyObject* o[10];
  long long n_original = 0, n_faces = 0;
  if (!PyArg_ParseTuple(args, "OOOOOOOOOOLL", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8],
                        &o[9], &n_original, &n_faces))
    return nullptr;
  static const char* names[] = {"pcol_records", "kill_data", "base", "tops", "top_at", "own_vertex",
                                "own_end", "own_position", "up", "corners"};
  auto h = std::make_unique<StreamHandle>();
  for (int i = 0; i < 10; ++i)
    if (!Take(o[i], names[i], i == 7 ? 'f' : 'i', 4, false, false, &h->tables[i])) return nullptr;
  HostArray* t = h->tables;
  const int64_t P = t[0].dims.size() == 2 ? t[0].dims[0] : -1, V0 = n_original, F = n_faces;
  if (P < 0 || t[0].dims[1] != 14) return Raise(ffi::Error::InvalidArgument("pcol_records must have shape [P, 14]")), nullptr;
  const int64_t K = t[1].dims.size() == 2 ? t[1].dims[0] : -1, B = t[2].dims.size() == 2 ? t[2].dims[0] : -1;
  const int64_t T = t[3].dims.size() == 2 ? t[3].dims[0] : -1;
  if (K < 0 || t[1].dims[1] != 4 || B < 0 || t[2].dims[1] != 4 || T < 0 || t[3].dims[1] != 5 || V0 < 0 || F < 0 ||
      K + B > F) {
    PyErr_SetString(PyExc_ValueError, "mesh_stream_new: kill_data, base [n, 4] and tops [n, 5] must fit the faces");
    return nullptr;
  }
  // A face's corners are numbered 3 * slot + c in int32.
  if (F > INT32_MAX / 3) {
    PyErr_Format(PyExc_ValueError, "mesh_stream_new: %lld faces are more than %d", (long long)F, INT32_MAX / 3);
    return nullptr;
  }
  if (!Raise(Expect("top_at", t[4].shape(), {T})) || !Raise(Expect("own_vertex", t[5].shape(), {P})) ||
      !Raise(Expect("own_end", t[6].shape(), {P})) || !Raise(Expect("own_position", t[7].shape(), {P, 3})) ||
      !Raise(Expect("up", t[8].shape(), {P + V0})) || !Raise(Expect("corners", t[9].shape(), {F, 3})))
    return nullptr;
  // Every index the stream follows stays inside its table.
  const PmxPcolRecord* records = reinterpret_cast<const PmxPcolRecord*>(t[0].data<int32_t>());
  for (int64_t q = 0; q < P; ++q)
    if (!pmx_pcol_record_fits(records + q, q, K, V0, P)) {
      PyErr_Format(PyExc_ValueError, "mesh_stream_new: pcol_records[%lld]: %s", (long long)q,
                   pmx_status_text(PMX_BAD_PCOL_RECORD));
      return nullptr;
    }
  const int32_t* up = t[8].data<int32_t>();
  for (int64_t i = 0; i < P + V0; ++i)
    if (up[i] < -1 || up[i] >= P || (i < P && up[i] >= i)) {
      PyErr_Format(PyExc_ValueError, "mesh_stream_new: up[%lld] = %d is not an earlier position", (long long)i, up[i]);
      return nullptr;
    }
  const int32_t* corners = t[9].data<int32_t>();
  for (int64_t i = 0; i < 3 * F; ++i)
    if (corners[i] < 0 || corners[i] >= V0) {
      PyErr_Format(PyExc_ValueError, "mesh_stream_new: corners[%lld] = %d is not an original vertex",
                   (long long)(i / 3), corners[i]);
      return nullptr;
    }
  const PmxFaceRecord* faces[2] = {reinterpret_cast<const PmxFaceRecord*>(t[1].data<int32_t>()),
                                   reinterpret_cast<const PmxFaceRecord*>(t[2].data<int32_t>())};
  for (int k = 0; k < 2; ++k)
    for (int64_t i = 0; i < (k ? B : K); ++i)
      if (!pmx_face_record_fits(faces[k] + i, F, V0)) {
        PyErr_Format(PyExc_ValueError, "mesh_stream_new: %s[%lld]: %s", names[1 + k], (long long)i,
                     pmx_status_text(k ? PMX_BAD_BASE_RECORD : PMX_BAD_KILL_RECORD));
        return nullptr;
      }
  const PmxFrontVertex* tops = reinterpret_cast<const PmxFrontVertex*>(t[3].data<int32_t>());
  const int32_t* top_at = t[4].data<int32_t>();
  for (int64_t i = 0; i < T; ++i)
    if (!pmx_top_fits(tops + i, top_at[i], V0, P)) {
      PyErr_Format(PyExc_ValueError, "mesh_stream_new: tops[%lld]: %s", (long long)i,
                   pmx_status_text(PMX_BAD_TOP_RECORD));
      return nullptr;
    }
  PmxStreamTables tables{records, faces[0], faces[1], tops, top_at, t[5].data<int32_t>(), t[6].data<int32_t>(),
                         t[7].data<float>(), up, corners, K, B, T, V0, P, F};
  PmxStatus status = PMX_OK;
  h->stream = pmx_mesh_stream_new(&tables, &status);
  if (!h->stream) {
    PyErr_Format(status == PMX_NO_MEMORY ? PyExc_MemoryError : PyExc_ValueError,
                 "mesh_stream_new: the base faces' corners have no top above them (%s)", pmx_status_text(status));
    return nullptr;
  }
  h->n_pcols = P;
  PyObject* capsule = PyCapsule_New(h.get(), kStreamCapsule, FreeStream);
  if (capsule) h.release();
  return capsule;
}

// The stream's counts after a step and its change packed side by side in
// one bytearray (the caller's to keep; NumPy views it without a copy):
// s32 face slots [k], s32 faces [k, 3], s32 vertex slots [u], s32 ids [u],
// f32 positions [u, 3].
PyObject* StreamState(const PmxMeshStream* s) {
  PmxStreamState st;
  pmx_mesh_stream_state(s, &st);
  const int64_t k = st.n_face_changes, u = st.n_vertex_changes;
  PyObject* packed = PyByteArray_FromStringAndSize(nullptr, (Py_ssize_t)(4 * (4 * k + 5 * u)));
  if (!packed) return nullptr;
  // A large change (a first frame, a cut) is gathered with the GIL released,
  // so other Python threads run meanwhile; a small one is not worth the
  // hand-over. The new bytearray is no one else's yet.
  char* out = PyByteArray_AS_STRING(packed);
  if (k + u > 4096) {
    Py_BEGIN_ALLOW_THREADS;
    pmx_mesh_stream_pack(s, out);
    Py_END_ALLOW_THREADS;
  } else {
    pmx_mesh_stream_pack(s, out);
  }
  return Py_BuildValue("(LLLLLLLLN)", (long long)st.n_face_slots, (long long)st.n_vertex_slots, (long long)k,
                       (long long)u, (long long)st.n_faces, (long long)st.n_vertices, (long long)st.n_used,
                       (long long)st.generation, packed);
}

// A failed step's exception (returns nullptr): MemoryError for memory, else
// ValueError, bad_size naming what PMX_BAD_SIZE means for the caller `who`.
PyObject* StreamError(const char* who, PmxStatus status, const char* bad_size) {
  PyErr_Format(status == PMX_NO_MEMORY ? PyExc_MemoryError : PyExc_ValueError, "%s: %s", who,
               status == PMX_BAD_SIZE    ? bad_size
               : status == PMX_NO_MEMORY ? "out of memory for the stream's slots"
                                         : "the frame's changes are not those of a refinement of this hierarchy; "
                                           "the stream is broken (make a new one)");
  return nullptr;
}

// mesh_stream_step(stream, positions, ran, frame, n, key)
//   -> (face slots, vertex slots, faces changed, vertices changed, faces, vertices, vertices used, generation,
//       the change packed: StreamState)
// The stream from the frame it holds to the next: its n visited slots'
// positions s32[L] and ran bits (u8 [L], or a word's u16 [L] and the frame's
// bit), key >= 0 naming lists that other frames share (a word), else -1.
// The caller keeps the arrays until the next step (the stream reads them
// as the frame it holds). A ValueError names what is wrong.
PyObject* MeshStreamStep(PyObject*, PyObject* args) {
  PyObject *stream_o, *positions_o, *ran_o;
  int frame = 0;
  long long n = 0, key = -1;
  if (!PyArg_ParseTuple(args, "OOOiLL", &stream_o, &positions_o, &ran_o, &frame, &n, &key)) return nullptr;
  auto* h = static_cast<StreamHandle*>(PyCapsule_GetPointer(stream_o, kStreamCapsule));
  if (!h) return nullptr;
  HostArray positions, ran;
  if (!Take(positions_o, "positions", 'i', 4, false, false, &positions) ||
      !Take(ran_o, "ran", 'u', 0, false, false, &ran))
    return nullptr;
  if (positions.dims.size() != 1 || ran.dims != positions.dims || n < 0 || n > positions.dims[0] ||
      n > h->n_pcols) {
    PyErr_Format(PyExc_ValueError,
                 "mesh_stream_step: positions and ran must have one shape [L], and n (%lld) at most L and P", n);
    return nullptr;
  }
  const bool words = ran.view.itemsize == 2;
  if (frame < 0 || frame >= (words ? PMX_FRAMES : 1)) {
    PyErr_Format(PyExc_ValueError, "mesh_stream_step: frame %d is not a bit of ran (%s)", frame,
                 words ? "a word's 16 frames" : "one frame");
    return nullptr;
  }
  PmxStreamFrame next{positions.data<int32_t>(), words ? nullptr : ran.data<uint8_t>(),
                      words ? ran.data<uint16_t>() : nullptr, frame, n, key < 0 ? -1 : key};
  PmxStatus status;
  Py_BEGIN_ALLOW_THREADS;
  status = pmx_mesh_stream_step(h->stream, &next);
  Py_END_ALLOW_THREADS;
  if (status != PMX_OK)
    return StreamError("mesh_stream_step", status,
                       "the frame's positions do not increase inside the hierarchy (the stream still holds the "
                       "last frame)");
  return StreamState(h->stream);
}

// mesh_stream_lane(stream, frame) -> as mesh_stream_step
// The stream to another frame (bit) of the word whose lists it holds: the
// arrays of the last step, kept by the caller, are not passed again.
PyObject* MeshStreamLane(PyObject*, PyObject* args) {
  PyObject* stream_o;
  int frame = 0;
  if (!PyArg_ParseTuple(args, "Oi", &stream_o, &frame)) return nullptr;
  auto* h = static_cast<StreamHandle*>(PyCapsule_GetPointer(stream_o, kStreamCapsule));
  if (!h) return nullptr;
  PmxStatus status;
  Py_BEGIN_ALLOW_THREADS;
  status = pmx_mesh_stream_lane(h->stream, frame);
  Py_END_ALLOW_THREADS;
  if (status != PMX_OK)
    return StreamError("mesh_stream_lane", status,
                       "the stream holds no word's lists, or frame is not one of its 16 bits (the stream still "
                       "holds the last frame)");
  return StreamState(h->stream);
}

// mesh_stream_compact(stream) -> bytearray
// The mesh held as Refinement.mesh() gives it, packed side by side (the
// caller's to keep; NumPy views it without a copy): s32 faces [faces, 3],
// s32 ids [used], f32 positions [used, 3] (the counts of the last step).
PyObject* MeshStreamCompact(PyObject*, PyObject* args) {
  PyObject* stream_o;
  if (!PyArg_ParseTuple(args, "O", &stream_o)) return nullptr;
  auto* h = static_cast<StreamHandle*>(PyCapsule_GetPointer(stream_o, kStreamCapsule));
  if (!h) return nullptr;
  PmxStreamState st;
  pmx_mesh_stream_state(h->stream, &st);
  PyObject* packed = PyByteArray_FromStringAndSize(nullptr, (Py_ssize_t)(12 * st.n_faces + 16 * st.n_used));
  if (!packed) return nullptr;
  auto* faces = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(packed));
  int32_t* ids = faces + 3 * st.n_faces;
  auto* positions = reinterpret_cast<float*>(ids + st.n_used);
  PmxStatus status;
  Py_BEGIN_ALLOW_THREADS;
  status = pmx_mesh_stream_compact(h->stream, faces, ids, positions);
  Py_END_ALLOW_THREADS;
  if (status != PMX_OK) {
    Py_DECREF(packed);
    PyErr_SetString(status == PMX_NO_MEMORY ? PyExc_MemoryError : PyExc_ValueError,
                    status == PMX_NO_MEMORY ? "mesh_stream_compact: out of memory to sort the changes"
                                            : "mesh_stream_compact: the stream is broken (a failed step); start a new MeshStream");
    return nullptr;
  }
  return packed;
}

// mesh_stream_arrays(stream) -> (face_vertex, face_id, vertex_id, vertex_position): read-only memoryviews
// of the stream's slots at their capacities, valid until a step grows them (the state's generation changes).
PyObject* MeshStreamArrays(PyObject*, PyObject* args) {
  PyObject* stream_o;
  if (!PyArg_ParseTuple(args, "O", &stream_o)) return nullptr;
  auto* h = static_cast<StreamHandle*>(PyCapsule_GetPointer(stream_o, kStreamCapsule));
  if (!h) return nullptr;
  PmxStreamState st;
  pmx_mesh_stream_state(h->stream, &st);
  auto view = [](const void* p, int64_t bytes) {
    static char empty[4];
    return PyMemoryView_FromMemory(const_cast<char*>(p ? static_cast<const char*>(p) : empty),
                                   p ? (Py_ssize_t)bytes : 0, PyBUF_READ);
  };
  return Py_BuildValue("(NNNN)", view(st.face_vertex, 12 * st.face_cap), view(st.face_id, 4 * st.face_cap),
                       view(st.vertex_id, 4 * st.vertex_cap), view(st.vertex_position, 12 * st.vertex_cap));
}

// mesh_stream_searches(stream) -> (at the split, from the vertex had, around, up): how many corners of new
// faces found their vertex each way since the stream was made.
PyObject* MeshStreamSearches(PyObject*, PyObject* args) {
  PyObject* stream_o;
  if (!PyArg_ParseTuple(args, "O", &stream_o)) return nullptr;
  auto* h = static_cast<StreamHandle*>(PyCapsule_GetPointer(stream_o, kStreamCapsule));
  if (!h) return nullptr;
  int64_t n[PMX_SEARCHES];
  pmx_mesh_stream_searches(h->stream, n);
  return Py_BuildValue("(LLLL)", (long long)n[PMX_SEARCH_SPLIT], (long long)n[PMX_SEARCH_HAD],
                       (long long)n[PMX_SEARCH_AROUND], (long long)n[PMX_SEARCH_UP]);
}

PyMethodDef methods[] = {
    {"targets", Targets, METH_NOARGS, "The XLA FFI targets of the core: {name: PyCapsule of the handler}."},
    {"simd", Simd, METH_VARARGS,
     "simd(level=-1): the SIMD kernels in use before; level >= 0 switches to the best up to it (0 plain, 1 AVX2, "
     "2 AVX-512)."},
    {"mesh_ranks", MeshRanks, METH_VARARGS,
     "mesh_ranks(mode=-1): how front_mesh took its ranks before; mode >= 0 sets it (0 by the ratio of items to "
     "bitmap words, 1 bitmaps always, 2 sorts always; every way gives the same mesh)."},
    {"simd_best", SimdBest, METH_NOARGS, "The best SIMD kernels this processor has (0 plain, 1 AVX2, 2 AVX-512)."},
    {"layout", Layout, METH_NOARGS, "The core's layout constants (pmx.h)."},
    {"drain", Drain, METH_NOARGS, "Frees the scratch the core keeps between calls."},
    {"refine_one", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(RefineOneEager)),
     METH_VARARGS | METH_KEYWORDS,
     "refine_one(rows, kills, order, camera, flags, n_roots, pcols, ran, positions, counts, unsure=None, "
     "answered=None, answers=None, level=-1): one camera eagerly, as the targets pmx_refine_one and "
     "pmx_refine_answered compute it (NumPy arrays in and out; ValueError naming a bad argument)."},
    {"front_mesh", FrontMeshEager, METH_VARARGS,
     "front_mesh(pcol_records, kill_data, base, tops, top_at, ran, positions, counts, item, n_original, "
     "n_faces_total, faces, ids, vertex_positions) -> n_ids: one refinement's mesh eagerly, as the target "
     "pmx_front_mesh reads it (NumPy arrays in and out; ValueError naming a bad argument)."},
    {"mesh_stream_new", MeshStreamNew, METH_VARARGS,
     "mesh_stream_new(pcol_records, kill_data, base, tops, top_at, own_vertex, own_end, own_position, up, corners, "
     "n_original, n_faces) -> stream: a drawable front mesh at the fully collapsed mesh (mesh_stream.c)."},
    {"mesh_stream_step", MeshStreamStep, METH_VARARGS,
     "mesh_stream_step(stream, positions, ran, frame, n, key) -> "
     "(face slots, vertex slots, faces changed, vertices changed, faces, vertices, vertices used, generation, "
     "change): the change a bytearray of s32 face slots [k], faces [k, 3], vertex slots [u], ids [u] and f32 "
     "positions [u, 3]."},
    {"mesh_stream_lane", MeshStreamLane, METH_VARARGS,
     "mesh_stream_lane(stream, frame) -> as mesh_stream_step: the stream to another frame (bit) of the word whose "
     "lists it holds."},
    {"mesh_stream_compact", MeshStreamCompact, METH_VARARGS,
     "mesh_stream_compact(stream) -> bytearray: the mesh held as Refinement.mesh() gives it, packed: s32 faces "
     "[faces, 3], s32 ids [used], f32 positions [used, 3]."},
    {"mesh_stream_arrays", MeshStreamArrays, METH_VARARGS,
     "mesh_stream_arrays(stream) -> read-only memoryviews (face_vertex, face_id, vertex_id, vertex_position) "
     "of the slots, valid until the generation changes."},
    {"mesh_stream_searches", MeshStreamSearches, METH_VARARGS,
     "mesh_stream_searches(stream) -> (at the split, from the vertex had, around, up): how many corners of new "
     "faces found their vertex each way."},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module = {PyModuleDef_HEAD_INIT, "_pmx", "The front engine's C core as XLA FFI targets (pmx.h).", -1,
                      methods, nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__pmx(void) { return PyModule_Create(&module); }
