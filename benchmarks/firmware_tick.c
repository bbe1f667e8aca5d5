/* Times vrs_tick for the device's config (vrs_protocol.h): batches of ticks on a moving plant,
 * ns per tick for each batch on stdout, one per line. argv: batches, ticks per batch, telemetry Hz. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "vrs_core.h"

static vrs_core core;

int main(int argc, char **argv)
{
    vrs_config cfg = {VRS_DEVICE_N_HINGES, VRS_DEVICE_LOOP_RATE_HZ, 0, VRS_DEVICE_MAX_TELEMETRY_HZ,
                      VRS_DEVICE_LIMIT_COUNTS, VRS_DEVICE_LIMIT_MARGIN_COUNTS, VRS_DEVICE_STALL_DUTY,
                      VRS_DEVICE_STALL_COUNTS, VRS_DEVICE_STALL_MS, VRS_DEVICE_OVERCURRENT_MA,
                      VRS_DEVICE_DRIVE_CAP_MV, {0, 0, 0}};
    vrs_gains g = {VRS_DEVICE_KP, VRS_DEVICE_KI, VRS_DEVICE_KD, VRS_DEVICE_CUTOFF_HZ, VRS_DEVICE_INTEGRAL_LIMIT,
                   VRS_DEVICE_DEADBAND, VRS_DEVICE_HOLD_BAND};
    vrs_gains gains[VRS_MAX_HINGES];
    int32_t counts[VRS_MAX_HINGES] = {0}, targets[VRS_MAX_HINGES];
    float duty[VRS_MAX_HINGES], pos[VRS_MAX_HINGES] = {0};
    uint8_t decay[VRS_MAX_HINGES], sink[VRS_TX_CAP];
    long batches = argc > 1 ? atol(argv[1]) : 200, per = argc > 2 ? atol(argv[2]) : 1000;
    int k;
    long b, i;
    uint32_t now = 0;
    for (k = 0; k < VRS_MAX_HINGES; k++) {
        gains[k] = g;
        targets[k] = 300 - 100 * k;
    }
    vrs_init(&core, &cfg, gains, counts);
    vrs_set_telemetry_rate(&core, (uint16_t)(argc > 3 ? atoi(argv[3]) : 0));
    for (b = 0; b < batches; b++) {
        struct timespec t0, t1;
        if (b % 20 == 0) {  /* a new move every 20 batches */
            for (k = 0; k < VRS_MAX_HINGES; k++)
                targets[k] = -targets[k];
            vrs_set_targets(&core, targets, now);
        }
        clock_gettime(CLOCK_MONOTONIC, &t0);
        for (i = 0; i < per; i++) {
            vrs_tick(&core, now, counts, NULL, duty, decay);
            for (k = 0; k < VRS_DEVICE_N_HINGES; k++) {  /* a plant: speed proportional to duty */
                pos[k] += duty[k] * 5.0f;
                counts[k] = (int32_t)pos[k];
            }
            now += 1000;
        }
        clock_gettime(CLOCK_MONOTONIC, &t1);
        vrs_tx(&core, sink, sizeof sink);
        printf("%.2f\n", ((double)(t1.tv_sec - t0.tv_sec) * 1e9 + (double)(t1.tv_nsec - t0.tv_nsec)) / (double)per);
    }
    return 0;
}
