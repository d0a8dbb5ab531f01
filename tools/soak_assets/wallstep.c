/* wallstep: an LD_PRELOAD library that steps one process's WALL clock (CLOCK_REALTIME and what
 * is built on it: time(), gettimeofday()) by the offset in seconds written in the file named by
 * $WALLSTEP_FILE, read again at most every 100 ms. CLOCK_MONOTONIC, CLOCK_BOOTTIME and every
 * sleep are left alone: this is what an NTP step or an operator's `date -s` does to a process,
 * without stepping the whole machine's clock. tools/soak.py builds it with gcc and preloads it
 * into the daemon for its clock_step faults. (libfaketime was tried first: with its monotonic
 * clock left real, Python 3.11's time.sleep fails with EINVAL under it.) */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/time.h>
#include <time.h>

typedef int (*cg_t)(clockid_t, struct timespec *);
static cg_t real_cg;
static long long off_ns;
static long long next_read_ns;

static long long mono_ns(void) {
    struct timespec t;
    real_cg(CLOCK_MONOTONIC, &t);
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

static void refresh(void) {
    if (!real_cg) real_cg = (cg_t)dlsym(RTLD_NEXT, "clock_gettime");
    long long now = mono_ns();
    if (now < next_read_ns) return;
    next_read_ns = now + 100000000LL;
    const char *path = getenv("WALLSTEP_FILE");
    if (!path) return;
    FILE *f = fopen(path, "r");
    if (!f) return;
    double s;
    if (fscanf(f, "%lf", &s) == 1) off_ns = (long long)(s * 1e9);
    fclose(f);
}

static int shifted(clockid_t c) {
    return c == CLOCK_REALTIME || c == CLOCK_REALTIME_COARSE || c == CLOCK_TAI;
}

int clock_gettime(clockid_t c, struct timespec *ts) {
    refresh();
    int r = real_cg(c, ts);
    if (r == 0 && shifted(c) && off_ns) {
        long long ns = (long long)ts->tv_sec * 1000000000LL + ts->tv_nsec + off_ns;
        ts->tv_sec = ns / 1000000000LL;
        ts->tv_nsec = ns % 1000000000LL;
        if (ts->tv_nsec < 0) { ts->tv_nsec += 1000000000LL; ts->tv_sec -= 1; }
    }
    return r;
}

int gettimeofday(struct timeval *tv, void *tz) {
    struct timespec ts;
    (void)tz;
    int r = clock_gettime(CLOCK_REALTIME, &ts);
    if (r == 0 && tv) { tv->tv_sec = ts.tv_sec; tv->tv_usec = ts.tv_nsec / 1000; }
    return r;
}

time_t time(time_t *out) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    if (out) *out = ts.tv_sec;
    return ts.tv_sec;
}
