/* controller_rt.c - see controller_rt.h */
#define _GNU_SOURCE /* sched_setaffinity, CPU_SET */
#include "controller_rt.h"

#include <errno.h>
#include <sched.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>

ddyn_rt_state ddyn_rt_setup(int priority, int cpu, int lock_memory)
{
    ddyn_rt_state s;
    memset(&s, 0, sizeof s);
    s.cpu = -1;
    /* memory first: page faults in the loop are the largest latencies a locked process avoids */
    if (lock_memory) {
        if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
            s.memory_locked = 1;
        } else {
            fprintf(stderr, "ddyn_controller: warning: realtime.lock_memory: mlockall failed (%s); raise "
                            "LimitMEMLOCK / ulimit -l\n", strerror(errno));
            s.warnings += 1;
        }
    }
    if (cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cpu, &set);
        if (sched_setaffinity(0, sizeof set, &set) == 0) {
            s.cpu = cpu;
        } else {
            fprintf(stderr, "ddyn_controller: warning: realtime.cpu: cannot pin to CPU %d (%s)\n", cpu,
                    strerror(errno));
            s.warnings += 1;
        }
    }
    if (priority > 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = priority;
        if (sched_setscheduler(0, SCHED_FIFO, &sp) == 0) {
            s.fifo_priority = priority;
        } else {
            fprintf(stderr, "ddyn_controller: warning: realtime.priority: SCHED_FIFO %d not permitted (%s); "
                            "running with normal scheduling (needs CAP_SYS_NICE or LimitRTPRIO)\n",
                    priority, strerror(errno));
            s.warnings += 1;
        }
    }
    return s;
}

int64_t ddyn_rt_now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000 + (int64_t)t.tv_nsec;
}

void ddyn_rt_sleep_until(int64_t t_ns, volatile const sig_atomic_t *stop)
{
    struct timespec t;
    t.tv_sec = (time_t)(t_ns / 1000000000);
    t.tv_nsec = (long)(t_ns % 1000000000);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &t, NULL) == EINTR) {
        if (stop != NULL && *stop) {
            return;
        }
    }
}
