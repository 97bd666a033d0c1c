/*
 * controller_rt.h - the real-time set-up of ddyn_controller (Linux): memory locked, the CPU pinned,
 * SCHED_FIFO, and absolute-deadline sleeps on CLOCK_MONOTONIC. What the process is not permitted
 * to do (no CAP_SYS_NICE / RLIMIT_RTPRIO, RLIMIT_MEMLOCK too small) is a warning, never a failure:
 * the SIL and a developer's machine run the same binary without privileges. docs/deploy.md.
 */
#ifndef DDYN_CONTROLLER_RT_H
#define DDYN_CONTROLLER_RT_H

#include <signal.h>
#include <stdint.h>
#include <time.h>

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    int memory_locked;   /* mlockall(MCL_CURRENT | MCL_FUTURE) succeeded */
    int fifo_priority;   /* the SCHED_FIFO priority in effect, 0 = normal scheduling */
    int cpu;             /* the CPU pinned to, -1 = none */
    int warnings;        /* how many of the asked-for settings were not permitted */
} ddyn_rt_state;

/* Apply the settings (priority 0: keep normal scheduling; cpu < 0: no pinning); a refused setting
 * prints a warning naming it and the reason to stderr. Returns what is in effect. */
ddyn_rt_state ddyn_rt_setup(int priority, int cpu, int lock_memory);

/* CLOCK_MONOTONIC now, in nanoseconds. */
int64_t ddyn_rt_now_ns(void);

/* Sleep until the absolute CLOCK_MONOTONIC time t_ns (clock_nanosleep TIMER_ABSTIME; restarted
 * after a signal unless *stop is set). Returns at once when t_ns has passed. */
void ddyn_rt_sleep_until(int64_t t_ns, volatile const sig_atomic_t *stop);

#ifdef __cplusplus
}
#endif

#endif
