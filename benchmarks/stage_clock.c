/* A monotonic clock in seconds for MuJoCo's stage timers (mjcb_time): benchmarks/bench_twin.py times each
 * stage of the twin's own closed loop with it, where a Python callback would cost more than the stages. */
#define _POSIX_C_SOURCE 199309L
#include <time.h>

double stage_clock(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}
