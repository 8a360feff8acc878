/* The one SIMD dispatch: a table of kernels per level (PMX_SIMD_PLAIN, AVX2,
 * AVX512), the best the processor has chosen at first use, switchable for
 * tests (pmx_simd). The plain kernels are the specification and build on any
 * processor; the others give the same bits. */
#include "internal.h"

#if PMX_X86
#include <immintrin.h>
#endif

static const Kernels plain = {decide_perspective_plain,
                              decide_orthographic_plain,
                              decide_row_perspective_plain,
                              decide_row_orthographic_plain,
                              decide_row_settled_plain,
                              decide_fat_plain,
                              gather_plain,
                              push_block_plain,
                              push_word_block_plain,
                              fat_masks_plain,
                              resolve_plain,
                              resolve_word_plain,
                              front_mesh_plain};
#if PMX_X86
static const Kernels avx2 = {decide_perspective_avx2,
                             decide_orthographic_avx2,
                             decide_row_perspective_avx2,
                             decide_row_orthographic_avx2,
                             decide_row_settled_avx2,
                             decide_fat_avx2,
                             gather_avx2,
                             push_block_avx2,
                             push_word_block_plain,
                             fat_masks_avx2,
                             resolve_avx2,
                             resolve_word_avx2,
                             front_mesh_avx2};
static const Kernels avx512 = {decide_perspective_avx512,
                               decide_orthographic_avx512,
                               decide_row_perspective_avx512,
                               decide_row_orthographic_avx512,
                               decide_row_settled_avx512,
                               decide_fat_avx512,
                               gather_avx512,
                               push_block_avx512,
                               push_word_block_avx512,
                               fat_masks_avx512,
                               resolve_avx512,
                               resolve_word_avx512,
                               front_mesh_avx512};
#endif

int pmx_simd_best(void)
{
#if PMX_X86
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
        __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq") &&
        __builtin_cpu_supports("bmi2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("popcnt"))
        return PMX_SIMD_AVX512;
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("popcnt"))
        return PMX_SIMD_AVX2;
#endif
    return PMX_SIMD_PLAIN;
}

static const Kernels *table_of(int level)
{
#if PMX_X86
    if (level == PMX_SIMD_AVX512)
        return &avx512;
    if (level == PMX_SIMD_AVX2)
        return &avx2;
#endif
    (void)level;
    return &plain;
}

/* The level in use; -1 until the first call picks the best. Threads that
 * race at the first use store the same value. */
static int level_in_use = -1;

static int current_level(void)
{
    int level = __atomic_load_n(&level_in_use, __ATOMIC_ACQUIRE);
    if (level < 0) {
        level = pmx_simd_best();
        __atomic_store_n(&level_in_use, level, __ATOMIC_RELEASE);
    }
    return level;
}

const Kernels *pmx_kernels(void) { return table_of(current_level()); }

const Kernels *pmx_kernels_at(int level, int *used)
{
    const int best = pmx_simd_best();
    level = level < 0 ? current_level() : level < best ? level : best;
    *used = level;
    return table_of(level);
}

int pmx_simd(int level)
{
    const int was = current_level();
    if (level >= 0) {
        const int best = pmx_simd_best();
        __atomic_store_n(&level_in_use, level < best ? level : best, __ATOMIC_RELEASE);
    }
    return was;
}

unsigned subnormals_off(void)
{
#if PMX_X86
    const unsigned mode = _mm_getcsr();
    _mm_setcsr(mode | 0x8040); /* FTZ (bit 15) and DAZ (bit 6) */
    return mode;
#elif defined(__aarch64__) && defined(__GNUC__)
    uint64_t fpcr;
    __asm__ __volatile__("mrs %0, fpcr" : "=r"(fpcr));
    __asm__ __volatile__("msr fpcr, %0" : : "r"(fpcr | (1u << 24))); /* FZ */
    return (unsigned)fpcr;
#else
    return 0;
#endif
}

void subnormals_back(unsigned mode)
{
#if PMX_X86
    _mm_setcsr(mode);
#elif defined(__aarch64__) && defined(__GNUC__)
    const uint64_t fpcr = mode;
    __asm__ __volatile__("msr fpcr, %0" : : "r"(fpcr));
#else
    (void)mode;
#endif
}

const char *pmx_status_text(PmxStatus status)
{
    switch (status) {
    case PMX_OK:
        return "ok";
    case PMX_BAD_SIZE:
        return "a size or capacity that does not fit the hierarchy";
    case PMX_BAD_TABLE:
        return "the hierarchy's links are not a forest laid out breadth first";
    case PMX_NO_MEMORY:
        return "out of memory for the scratch";
    case PMX_FACES_DIFFER:
        return "the faces drawn do not match the refinement's face count";
    case PMX_FRONT_PAST:
        return "the slots' front holds more vertices than the original vertices (not a refinement's slots)";
    case PMX_START_TWICE:
        return "two vertices of the slots' front start at one original vertex (not a refinement's slots)";
    case PMX_FRONT_NOT_AT_0:
        return "the slots' front does not start at original vertex 0 (not a refinement's slots)";
    case PMX_FACE_TWICE:
        return "a face is drawn twice (slots or tables that are not a refinement's)";
    case PMX_VERTEX_TWICE:
        return "a vertex id is used by two vertices of the front (not a refinement's slots)";
    case PMX_BAD_PCOL_RECORD:
        return "a pcol record points outside the tables";
    case PMX_BAD_KILL_RECORD:
        return "a kill_data record is outside the faces or original vertices";
    case PMX_BAD_BASE_RECORD:
        return "a base record is outside the faces or original vertices";
    case PMX_BAD_TOP_RECORD:
        return "a top is outside the positions or vertices";
    }
    return "unknown status";
}
