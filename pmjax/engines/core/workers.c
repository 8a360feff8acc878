/* Helpers of one call: the caller and up to threads - 1 helpers scheduled by
 * the caller's runner work on a shared job (taking its items from a cursor).
 *
 * A helper may start late (its runner busy with other work) or, where the
 * runner has no thread to give, at once on the calling thread. The caller
 * waits only for the helpers that started before it finished its own share:
 * one that starts later finds the call closed and returns without touching
 * the job. So no call waits for a thread that is itself waiting, however
 * many calls share the runner's threads. */
#include <pthread.h>
#include <stdlib.h>

#include "internal.h"

typedef struct {
    pthread_mutex_t lock;
    pthread_cond_t idle;
    int refs, active, closed;
    void (*work)(void *);
    void *job;
} Shared;

/* Drops one reference (lock held); the last frees. */
static void release(Shared *sh)
{
    const int last = --sh->refs == 0;
    pthread_mutex_unlock(&sh->lock);
    if (last) {
        pthread_mutex_destroy(&sh->lock);
        pthread_cond_destroy(&sh->idle);
        free(sh);
    }
}

static void helper(void *arg)
{
    Shared *sh = arg;
    pthread_mutex_lock(&sh->lock);
    const int go = !sh->closed;
    sh->active += go;
    pthread_mutex_unlock(&sh->lock);
    if (go)
        sh->work(sh->job);
    pthread_mutex_lock(&sh->lock);
    if (go && --sh->active == 0)
        pthread_cond_signal(&sh->idle);
    release(sh);
}

void run_shared(const PmxRunner *runner, void (*work)(void *job), void *job)
{
    const int64_t helpers = runner && runner->schedule ? runner->threads - 1 : 0;
    Shared *sh = helpers > 0 ? calloc(1, sizeof(Shared)) : NULL;
    if (!sh) { /* no helper wanted (or no memory for them): the caller alone */
        work(job);
        return;
    }
    pthread_mutex_init(&sh->lock, NULL);
    pthread_cond_init(&sh->idle, NULL);
    sh->work = work, sh->job = job, sh->refs = (int)helpers + 1;
    for (int64_t i = 0; i < helpers; i++)
        runner->schedule(runner->ctx, helper, sh);
    work(job);
    pthread_mutex_lock(&sh->lock);
    sh->closed = 1;
    while (sh->active > 0)
        pthread_cond_wait(&sh->idle, &sh->lock);
    release(sh);
}
