/* Working memory: a pool of scratch, each in parts allocated when a call
 * first needs them, kept for the next call of any thread (fresh buffers would
 * cost their page faults again). */
#include <pthread.h>
#include <stdlib.h>

#include "internal.h"

/* Idle scratch kept at most. */
#define POOL_KEPT 8

static pthread_mutex_t pool_lock = PTHREAD_MUTEX_INITIALIZER;
static PmxScratch *pool = NULL;
static int pool_size = 0;

/* n elements of size bytes, zeroed (mark and bitmaps must start zero; the
 * other arrays are written before they are read, and calloc's pages are only
 * touched where a call writes). */
static void *zeros(int64_t n, size_t size) { return calloc((size_t)(n > 0 ? n : 1), size); }

static void free_sets(PmxScratch *s)
{
    void *parts[] = {s->set_visit, s->set_whole, s->set_yes, s->set_ran, s->set_unsure_lanes, s->set_unsure};
    for (size_t i = 0; i < sizeof parts / sizeof parts[0]; i++)
        free(parts[i]);
    s->set_visit = s->set_whole = s->set_yes = s->set_ran = s->set_unsure_lanes = NULL;
    s->set_unsure = NULL;
    s->sets = 0;
}

static void free_mesh(PmxScratch *s)
{
    void *parts[] = {s->not_run_at, s->start_prefix, s->face_prefix, s->vertex_prefix, s->start_block,
                     s->front_index, s->start_bits, s->face_bits, s->vertex_bits, s->start_sum, s->face_sum,
                     s->vertex_sum, s->front, s->front_rank, s->drawn, s->pairs[0], s->pairs[1], s->sort_counts};
    for (size_t i = 0; i < sizeof parts / sizeof parts[0]; i++)
        free(parts[i]);
    s->not_run_at = s->start_prefix = s->face_prefix = s->vertex_prefix = s->start_block = s->front_index = NULL;
    s->front_rank = NULL;
    s->start_bits = s->face_bits = s->vertex_bits = s->start_sum = s->face_sum = s->vertex_sum = NULL;
    s->front = NULL;
    s->drawn = NULL;
    s->pairs[0] = s->pairs[1] = NULL;
    s->sort_counts = NULL;
}

/* The slot parts (scratch_slots), freed and cleared. */
static void free_slots(PmxScratch *s)
{
    void *parts[] = {s->ids, s->kid, s->kill, s->pcols, s->unsure, s->parent, s->chain, s->state, s->ran, s->mark};
    for (size_t i = 0; i < sizeof parts / sizeof parts[0]; i++)
        free(parts[i]);
    s->ids = s->kid = s->kill = s->pcols = s->unsure = s->parent = s->chain = NULL;
    s->state = s->ran = s->mark = NULL;
}

/* The word parts (scratch_words), freed and cleared. */
static void free_words(PmxScratch *s)
{
    void *parts[] = {s->visit, s->whole, s->yes, s->ran_frames, s->unsure_lanes};
    for (size_t i = 0; i < sizeof parts / sizeof parts[0]; i++)
        free(parts[i]);
    s->visit = s->whole = s->yes = s->ran_frames = s->unsure_lanes = NULL;
}

/* Everything a scratch holds, through each group's own list (the one its
 * allocation frees on failure, so none is left out). */
static void free_parts(PmxScratch *s)
{
    free_slots(s);
    free_words(s);
    free_mesh(s);
    free_sets(s);
}

int scratch_slots(PmxScratch *s)
{
    if (s->ids)
        return 1;
    const int64_t P = s->n_pcols, room = P + PMX_SPARE;
    s->ids = zeros(room, sizeof(int32_t));
    s->kid = zeros(2 * room, sizeof(int32_t));
    s->kill = zeros(room, sizeof(int32_t));
    s->pcols = zeros(room, sizeof(int32_t));
    s->unsure = zeros(room, sizeof(int32_t));
    s->parent = zeros(room, sizeof(int32_t));
    s->chain = zeros(room, sizeof(int32_t));
    s->state = zeros(room, 1);
    s->ran = zeros(room, 1);
    s->mark = zeros(room, 1);
    if (!(s->ids && s->kid && s->kill && s->pcols && s->unsure && s->parent && s->chain && s->state && s->ran &&
          s->mark)) {
        free_slots(s);
        return 0;
    }
    return 1;
}

int scratch_words(PmxScratch *s)
{
    if (s->visit)
        return 1;
    const int64_t room = s->n_pcols + PMX_SPARE;
    s->whole = zeros(room, sizeof(Lanes));
    s->yes = zeros(room, sizeof(Lanes));
    s->ran_frames = zeros(room, sizeof(Lanes));
    s->unsure_lanes = zeros(room, sizeof(Lanes));
    s->visit = zeros(room, sizeof(Lanes));
    if (!(s->whole && s->yes && s->ran_frames && s->unsure_lanes && s->visit)) {
        free_words(s);
        return 0;
    }
    return 1;
}

int scratch_sets(PmxScratch *s, int64_t sets)
{
    if (s->set_visit && s->sets >= sets)
        return 1;
    free_sets(s);
    const int64_t room = (s->n_pcols + PMX_SPARE) * sets;
    s->set_visit = zeros(room, sizeof(Lanes));
    s->set_whole = zeros(room, sizeof(Lanes));
    s->set_yes = zeros(room, sizeof(Lanes));
    s->set_ran = zeros(room, sizeof(Lanes));
    s->set_unsure_lanes = zeros(room, sizeof(Lanes));
    s->set_unsure = zeros(room, sizeof(int32_t));
    if (!(s->set_visit && s->set_whole && s->set_yes && s->set_ran && s->set_unsure_lanes && s->set_unsure)) {
        free_sets(s);
        return 0;
    }
    s->sets = sets;
    return 1;
}

int scratch_mesh(PmxScratch *s, int64_t n_original, int64_t n_faces)
{
    if (s->front && s->n_original >= n_original && s->n_faces >= n_faces)
        return 1;
    free_mesh(s);
    const int64_t V0 = n_original, P = s->n_pcols;
    s->n_original = V0, s->n_faces = n_faces;
    const int64_t start_words = V0 / 64 + 1, face_words = n_faces / 64 + 1, vertex_words = (V0 + P) / 64 + 1;
    s->not_run_at = zeros(P, sizeof(int32_t));
    s->start_bits = zeros(start_words, sizeof(uint64_t));
    s->face_bits = zeros(face_words, sizeof(uint64_t));
    s->vertex_bits = zeros(vertex_words, sizeof(uint64_t));
    s->start_sum = zeros(start_words / 64 + 1, sizeof(uint64_t));
    s->face_sum = zeros(face_words / 64 + 1, sizeof(uint64_t));
    s->vertex_sum = zeros(vertex_words / 64 + 1, sizeof(uint64_t));
    s->start_prefix = zeros(start_words, sizeof(int32_t));
    s->face_prefix = zeros(face_words, sizeof(int32_t));
    s->vertex_prefix = zeros(vertex_words, sizeof(int32_t));
    s->start_block = zeros(start_words / 64 + 1, sizeof(int32_t));
    s->front_rank = zeros(V0, sizeof(int32_t));
    s->drawn = zeros(n_faces, sizeof(PmxFaceRecord));
    s->front_index = zeros(V0, sizeof(int32_t));
    s->front = zeros(V0 + 1, sizeof(PmxFrontVertex)); /* one slot past the front */
    const int64_t pairs = n_faces > V0 + 1 ? n_faces : V0 + 1;
    s->pairs[0] = zeros(pairs, sizeof(IdSlot));
    s->pairs[1] = zeros(pairs, sizeof(IdSlot));
    s->sort_counts = zeros(RANK_COUNTS, sizeof(int32_t));
    if (!(s->not_run_at && s->start_bits && s->face_bits && s->vertex_bits && s->start_sum && s->face_sum &&
          s->vertex_sum && s->start_prefix && s->face_prefix && s->vertex_prefix && s->start_block && s->front_rank &&
          s->drawn && s->front_index && s->front && s->pairs[0] && s->pairs[1] && s->sort_counts)) {
        free_mesh(s);
        return 0;
    }
    return 1;
}

PmxScratch *pmx_scratch_take(int64_t n_pcols)
{
    pthread_mutex_lock(&pool_lock);
    /* The first idle scratch made for this many pcols (buffers sized for a
     * larger hierarchy would be reused too, but their pages are cold). */
    PmxScratch **at = &pool;
    while (*at && (*at)->n_pcols != n_pcols)
        at = &(*at)->next;
    PmxScratch *s = *at;
    if (s) {
        *at = s->next;
        pool_size--;
    }
    pthread_mutex_unlock(&pool_lock);
    if (!s) {
        s = calloc(1, sizeof(PmxScratch));
        if (s)
            s->n_pcols = n_pcols;
    }
    return s;
}

void pmx_scratch_give(PmxScratch *s)
{
    PmxScratch *dropped = NULL;
    pthread_mutex_lock(&pool_lock);
    s->next = pool;
    pool = s;
    if (++pool_size > POOL_KEPT) {
        /* The oldest idle scratch goes. */
        PmxScratch **at = &pool;
        while ((*at)->next)
            at = &(*at)->next;
        dropped = *at;
        *at = NULL;
        pool_size--;
    }
    pthread_mutex_unlock(&pool_lock);
    if (dropped) {
        free_parts(dropped);
        free(dropped);
    }
}

void pmx_scratch_drain(void)
{
    pthread_mutex_lock(&pool_lock);
    PmxScratch *s = pool;
    pool = NULL;
    pool_size = 0;
    pthread_mutex_unlock(&pool_lock);
    while (s) {
        PmxScratch *next = s->next;
        free_parts(s);
        free(s);
        s = next;
    }
}
