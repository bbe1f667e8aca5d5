/* Feeds each corpus file to a fresh firmware core, in chunks, between control ticks; then a
 * GET_STATE frame, whose STATE reply must come back. Built with -fsanitize=address,undefined by
 * tests/firmware/test_firmware_wire.py. Exit 0: every file survived; 1: a core stopped answering. */
#include <stdio.h>
#include <string.h>

#include "vrs_core.h"

static vrs_core core;
static uint8_t data[1 << 16];

int main(int argc, char **argv)
{
    vrs_config cfg = VRS_DEVICE_CONFIG;
    vrs_gains g = VRS_DEVICE_GAINS;
    vrs_gains gains[VRS_MAX_HINGES];
    int32_t counts[VRS_MAX_HINGES] = {0};
    float duty[VRS_MAX_HINGES];
    uint8_t decay[VRS_MAX_HINGES], out[VRS_TX_CAP], frame[64], id, n;
    uint32_t values[VRS_MAX_FIELDS], now = 0, pos, len, k, got;
    uint16_t seq;
    int a, found;
    for (k = 0; k < VRS_MAX_HINGES; k++)
        gains[k] = g;
    for (a = 1; a < argc; a++) {
        FILE *f = fopen(argv[a], "rb");
        if (f == NULL)
            return 2;
        len = (uint32_t)fread(data, 1, sizeof data, f);
        fclose(f);
        if (vrs_init(&core, &cfg, gains, counts) != 0)
            return 2;
        for (pos = 0; pos < len;) {
            uint32_t chunk = 1 + data[pos] % 97;
            if (chunk > len - pos)
                chunk = len - pos;
            vrs_rx(&core, data + pos, chunk, now);
            pos += chunk;
            counts[pos % VRS_DEVICE_N_HINGES] = (int32_t)(pos % 900) - 450;
            vrs_tick(&core, now, counts, NULL, duty, decay);
            now += 1000;
            vrs_tx(&core, out, sizeof out);
        }
        frame[0] = 0;
        len = 1 + vrs_encode(VRS_MSG_GET_STATE, 0xBEEF, values, 0, frame + 1, sizeof frame - 1);
        vrs_rx(&core, frame, len, now);
        got = vrs_tx(&core, out, sizeof out);
        found = 0;
        for (pos = 0, k = 0; k < got; k++)
            if (out[k] == 0) {
                if (vrs_decode(out + pos, k - pos, &id, &seq, values, &n) == 0 && id == VRS_MSG_STATE && seq == 0xBEEF)
                    found = 1;
                pos = k + 1;
            }
        if (!found) {
            fprintf(stderr, "%s: no STATE reply after the corpus\n", argv[a]);
            return 1;
        }
    }
    return 0;
}
