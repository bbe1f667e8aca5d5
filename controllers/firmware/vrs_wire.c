/* The wire codec of docs/protocol.md: CRC-16/CCITT-FALSE, COBS, and message bodies packed and
 * unpacked from the layout table in vrs_protocol.h (generated from twin/link/protocol.py). */
#include <string.h>

#include "vrs_core.h"

typedef struct {
    uint8_t id;
    const char *codes;          /* fixed fields: B H I h i */
    const char *hinge_codes;    /* per-hinge fields after the count byte; "" if none */
} vrs_layout;

#define VRS_LAYOUT_ROW(name, codes, hinge_codes) {VRS_MSG_##name, codes, hinge_codes},
static const vrs_layout LAYOUTS[] = {VRS_MESSAGES(VRS_LAYOUT_ROW)};
#define N_LAYOUTS (sizeof LAYOUTS / sizeof LAYOUTS[0])

static const vrs_layout *layout_of(uint8_t id)
{
    uint32_t i;
    for (i = 0; i < N_LAYOUTS; i++)
        if (LAYOUTS[i].id == id)
            return &LAYOUTS[i];
    return NULL;
}

static uint32_t code_size(char code)
{
    switch (code) {
    case 'B': return 1;
    case 'H': case 'h': return 2;
    default: return 4;  /* I, i */
    }
}

static uint32_t codes_size(const char *codes)
{
    uint32_t s = 0;
    for (; *codes; codes++)
        s += code_size(*codes);
    return s;
}

/* CRC-16/CCITT-FALSE four bits at a time: CRC_NIBBLE[i] is the CRC register's update for nibble i */
static const uint16_t CRC_NIBBLE[16] = {0x0000, 0x1021, 0x2042, 0x3063, 0x4084, 0x50A5, 0x60C6, 0x70E7,
                                        0x8108, 0x9129, 0xA14A, 0xB16B, 0xC18C, 0xD1AD, 0xE1CE, 0xF1EF};

uint16_t vrs_crc16(const uint8_t *data, uint32_t n)
{
    uint16_t c = 0xFFFFu;
    uint32_t i;
    for (i = 0; i < n; i++) {
        c = (uint16_t)((c << 4) ^ CRC_NIBBLE[(c >> 12) ^ (data[i] >> 4)]);
        c = (uint16_t)((c << 4) ^ CRC_NIBBLE[(c >> 12) ^ (data[i] & 0x0Fu)]);
    }
    return c;
}

uint32_t vrs_cobs_encode(const uint8_t *in, uint32_t n, uint8_t *out)
{
    uint32_t code_at = 0, len = 1, i;
    uint8_t code = 1;
    for (i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = len++;
            code = 1;
        } else {
            out[len++] = in[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = len++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return len;
}

int32_t vrs_cobs_decode(const uint8_t *in, uint32_t n, uint8_t *out)
{
    uint32_t i = 0, len = 0, j;
    while (i < n) {
        uint8_t code = in[i];
        if (code == 0 || i + code > n)
            return -1;
        for (j = i + 1; j < i + code; j++) {
            if (in[j] == 0)
                return -1;
            out[len++] = in[j];
        }
        i += code;
        if (code != 0xFF && i < n)
            out[len++] = 0;
    }
    return (int32_t)len;
}

static uint32_t put(uint8_t *p, char code, uint32_t v)
{
    uint32_t k, s = code_size(code);
    for (k = 0; k < s; k++)
        p[k] = (uint8_t)(v >> (8 * k));
    return s;
}

static uint32_t get(const uint8_t *p, char code)
{
    switch (code) {
    case 'B': return p[0];
    case 'H': return (uint32_t)p[0] | (uint32_t)p[1] << 8;
    case 'h': return (uint32_t)(int32_t)(int16_t)((uint16_t)(p[0] | p[1] << 8));
    default: return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
    }
}

uint32_t vrs_encode(uint8_t msg_id, uint16_t seq, const uint32_t *values, uint8_t n, uint8_t *out, uint32_t max)
{
    uint8_t payload[VRS_MAX_PAYLOAD];
    const vrs_layout *lay = layout_of(msg_id);
    const char *c;
    uint32_t len = 4, v = 0, k;
    uint16_t crc;
    if (lay == NULL)
        return 0;
    if (*lay->hinge_codes == '\0')
        n = 0;
    if (4 + codes_size(lay->codes) + (n ? 1 : 0) + n * codes_size(lay->hinge_codes) + 2 > VRS_MAX_PAYLOAD)
        return 0;
    payload[0] = VRS_PROTOCOL_VERSION;
    payload[1] = msg_id;
    payload[2] = (uint8_t)seq;
    payload[3] = (uint8_t)(seq >> 8);
    for (c = lay->codes; *c; c++)
        len += put(payload + len, *c, values[v++]);
    if (*lay->hinge_codes) {
        payload[len++] = n;
        for (c = lay->hinge_codes; *c; c++)
            for (k = 0; k < n; k++)
                len += put(payload + len, *c, values[v++]);
    }
    crc = vrs_crc16(payload, len);
    payload[len++] = (uint8_t)crc;
    payload[len++] = (uint8_t)(crc >> 8);
    if (len + len / 254 + 2 > max)
        return 0;
    len = vrs_cobs_encode(payload, len, out);
    out[len++] = 0;
    return len;
}

int vrs_decode(const uint8_t *frame, uint32_t len, uint8_t *msg_id, uint16_t *seq, uint32_t *values, uint8_t *n)
{
    uint8_t payload[VRS_RX_CAP];
    const vrs_layout *lay;
    const char *c;
    int32_t plen;
    uint32_t pos = 4, v = 0, k, fixed, per;
    if (len > VRS_RX_CAP)
        return VRS_DROP_COBS;
    plen = vrs_cobs_decode(frame, len, payload);
    if (plen < 0 || plen > VRS_MAX_PAYLOAD) /* over the maximum payload: garbage, as the docs say */
        return VRS_DROP_COBS;
    if (plen < 6)
        return VRS_DROP_SHORT;
    if (vrs_crc16(payload, (uint32_t)plen - 2) != (uint16_t)(payload[plen - 2] | payload[plen - 1] << 8))
        return VRS_DROP_CRC;
    *msg_id = payload[1];
    *seq = (uint16_t)(payload[2] | payload[3] << 8);
    *n = 0;
    if (payload[0] != VRS_PROTOCOL_VERSION)
        return VRS_NACK_BAD_VERSION;
    lay = layout_of(payload[1]);
    if (lay == NULL)
        return VRS_NACK_UNKNOWN_MESSAGE;
    plen -= 2;
    fixed = 4 + codes_size(lay->codes);
    per = codes_size(lay->hinge_codes);
    if (per) {
        if ((uint32_t)plen < fixed + 1)
            return VRS_NACK_BAD_LENGTH;
        *n = payload[fixed];
        fixed += 1;
    }
    if ((uint32_t)plen != fixed + *n * per || *n > VRS_MAX_HINGES)
        return VRS_NACK_BAD_LENGTH;
    for (c = lay->codes; *c; c++) {
        values[v++] = get(payload + pos, *c);
        pos += code_size(*c);
    }
    if (per) {
        pos++;
        for (c = lay->hinge_codes; *c; c++)
            for (k = 0; k < *n; k++) {
                values[v++] = get(payload + pos, *c);
                pos += code_size(*c);
            }
    }
    return 0;
}
