/* Preloaded before Debian's libfaketime 0.9.10 by tests/faults/test_clock.py: its waits on the
 * monotonic clock, which FAKETIME_DONT_FAKE_MONOTONIC=1 leaves unfaked, go straight to glibc.
 *
 * - clock_nanosleep: libfaketime#426 (fixed upstream after 0.9.10): a TIMER_ABSTIME deadline on
 *   CLOCK_MONOTONIC is moved by the faked offset, the kernel gets a negative time, EINVAL:
 *   Python 3.11's time.sleep() fails.
 * - pthread_cond_timedwait on a condition variable of CLOCK_MONOTONIC (Python's GIL): the
 *   deadline is mistranslated and a thread waiting for the GIL waits up to 0.5 s instead of the
 *   5 ms switch interval (a 200 Hz loop sharing a process with a serial thread stalls).
 * Every other clock's waits go on to libfaketime, which fakes them. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <pthread.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#define COND_CLOCK_MONOTONIC 2u /* glibc >= 2.25: the clock bit of pthread_cond_t.__wrefs */

int clock_nanosleep(clockid_t clock_id, int flags, const struct timespec *req,
                    struct timespec *rem) {
  static int (*next)(clockid_t, int, const struct timespec *, struct timespec *);
  if (clock_id == CLOCK_MONOTONIC || clock_id == CLOCK_BOOTTIME)
    return syscall(SYS_clock_nanosleep, clock_id, flags, req, rem) == 0 ? 0 : errno;
  if (!next)
    next = (int (*)(clockid_t, int, const struct timespec *, struct timespec *))dlsym(
        RTLD_NEXT, "clock_nanosleep");
  return next(clock_id, flags, req, rem);
}

typedef int (*timedwait_fn)(pthread_cond_t *, pthread_mutex_t *, const struct timespec *);

int pthread_cond_timedwait(pthread_cond_t *cond, pthread_mutex_t *mutex,
                           const struct timespec *abstime) {
  static timedwait_fn glibc, next;
  if (!glibc) {
    void *libc = dlopen("libc.so.6", RTLD_LAZY | RTLD_NOLOAD);
    glibc = (timedwait_fn)dlvsym(libc, "pthread_cond_timedwait", "GLIBC_2.3.2");
    next = (timedwait_fn)dlvsym(RTLD_NEXT, "pthread_cond_timedwait", "GLIBC_2.3.2");
  }
  if (__atomic_load_n(&cond->__data.__wrefs, __ATOMIC_RELAXED) & COND_CLOCK_MONOTONIC)
    return glibc(cond, mutex, abstime);
  return next(cond, mutex, abstime);
}
