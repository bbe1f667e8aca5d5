/* The supervisor: commands from the host, states and faults, the control tick, telemetry.
 * docs/protocol.md is the contract; docs/firmware.md the architecture. */
#include <string.h>

#include "vrs_core.h"
#include "vrs_layout.h"

/* ---- small helpers -------------------------------------------------------------------- */

static uint32_t round_to_u32(float x) { return x <= 0.0f ? 0u : (uint32_t)(x + 0.5f); }

static int16_t duty_to_wire(float d)
{
    float x = d * (float)VRS_DUTY_SCALE;
    return (int16_t)(x >= 0.0f ? x + 0.5f : x - 0.5f);
}

static int out_of(float x, float lo, float hi) { return !(x >= lo && x <= hi); }

static int gains_valid(const vrs_gains *g)
{
    return !(out_of(g->kp, VRS_BOUND_KP_MIN, VRS_BOUND_KP_MAX) || out_of(g->ki, VRS_BOUND_KI_MIN, VRS_BOUND_KI_MAX)
             || out_of(g->kd, VRS_BOUND_KD_MIN, VRS_BOUND_KD_MAX)
             || out_of(g->cutoff_hz, VRS_BOUND_DERIVATIVE_CUTOFF_MIN, VRS_BOUND_DERIVATIVE_CUTOFF_MAX)
             || out_of(g->integral_limit, VRS_BOUND_INTEGRAL_LIMIT_MIN, VRS_BOUND_INTEGRAL_LIMIT_MAX)
             || out_of(g->deadband, VRS_BOUND_DEADBAND_DUTY_MIN, VRS_BOUND_DEADBAND_DUTY_MAX)
             || (int32_t)g->hold_band - VRS_BOUND_HOLD_BAND_MIN < 0 || g->hold_band > VRS_BOUND_HOLD_BAND_MAX);
}

/* a SET_GAINS block (its 7 fields as the wire carries them) within the bounds, compared in wire units: decoded to
 * float first, a value at a bound could land a rounding past it (a deadband of 0.5 the host passes, 16384, is
 * 0.500015) */
static int wire_gains_valid(const uint32_t *v)
{
    static const int32_t lo[] = VRS_WIRE_GAINS_MIN, hi[] = VRS_WIRE_GAINS_MAX;
    uint8_t i;
    for (i = 0; i < sizeof lo / sizeof lo[0]; i++)
        if ((int32_t)v[i] < lo[i] || (int32_t)v[i] > hi[i])  /* kp, ki, kd signed; the rest 16 bits */
            return 0;
    return 1;
}

/* ---- transmit queue (ring) ------------------------------------------------------------ */

/* queue n bytes whole, or nothing (0) when they would leave less than `spare` bytes free */
static int queue(vrs_core *c, const uint8_t *bytes, uint32_t n, uint32_t spare)
{
    uint32_t at, first;
    if (n == 0 || c->tx_len + n + spare > VRS_TX_CAP)
        return 0;
    at = (c->tx_head + c->tx_len) % VRS_TX_CAP;
    first = VRS_TX_CAP - at < n ? VRS_TX_CAP - at : n;
    memcpy(c->tx_buf + at, bytes, first);
    memcpy(c->tx_buf, bytes + first, n - first);
    c->tx_len += n;
    return 1;
}

uint32_t vrs_tx(vrs_core *c, uint8_t *out, uint32_t max)
{
    uint32_t n = c->tx_len < max ? c->tx_len : max;
    uint32_t first = VRS_TX_CAP - c->tx_head < n ? VRS_TX_CAP - c->tx_head : n;
    memcpy(out, c->tx_buf + c->tx_head, first);
    memcpy(out + first, c->tx_buf, n - first);
    c->tx_head = (c->tx_head + n) % VRS_TX_CAP;
    c->tx_len -= n;
    return n;
}

/* commands that act: their replies are kept for repeats; queries are answered afresh. ESTOP is not one:
 * it runs every time it arrives, so a late retry (after a CLEAR_FAULT and new targets) stops the device
 * again instead of being answered from a reply kept for it (docs/protocol.md, "Repeats"). */
static int acts(uint8_t id)
{
    return id == VRS_MSG_SET_TARGETS || id == VRS_MSG_SET_GAINS || id == VRS_MSG_CLEAR_FAULT
           || id == VRS_MSG_SET_TELEMETRY_RATE || id == VRS_MSG_CONFIRM_ZERO || id == VRS_MSG_PULSE
           || id == VRS_MSG_SET_WIRING
           || id == VRS_MSG_PROGRAM;
}

/* queue a reply to the command (request id, seq, frame CRC); keep it if the command acts */
static void reply(vrs_core *c, uint8_t request, uint16_t seq, uint16_t request_crc, uint8_t id,
                  const uint32_t *values, uint8_t n)
{
    uint8_t frame_bytes[VRS_MAX_PAYLOAD + VRS_MAX_PAYLOAD / 254 + 2];
    uint32_t len = vrs_encode(id, seq, values, n, frame_bytes, sizeof frame_bytes);
    vrs_reply *r = &c->replies[c->reply_next];
    queue(c, frame_bytes, len, 0);
    if (!acts(request) || len == 0 || len > VRS_REPLY_CAP)
        return;
    memcpy(r->payload, frame_bytes, len);
    r->used = 1;
    r->seq = seq;
    r->at_us = c->now_us;
    r->request_crc = request_crc;
    r->len = (uint16_t)len;
    c->reply_next = (uint8_t)((c->reply_next + 1) % VRS_REPLY_MEMORY);
}

static void ack(vrs_core *c, uint16_t seq, uint16_t crc, uint8_t acked)
{
    uint32_t v[2];
    v[0] = acked;
    v[1] = c->now_us;
    reply(c, acked, seq, crc, VRS_MSG_ACK, v, 0);
}

static void nack(vrs_core *c, uint16_t seq, uint16_t crc, uint8_t acked, int reason, uint32_t detail)
{
    uint32_t v[3];
    v[0] = acked;
    v[1] = (uint32_t)reason;
    v[2] = detail & 0xFFu;
    reply(c, acked, seq, crc, VRS_MSG_NACK, v, 0);
}

/* ---- supervisor ------------------------------------------------------------------------ */

static void fault(vrs_core *c, uint16_t flag, uint8_t hinge)
{
    c->state = flag == VRS_FAULT_ESTOP ? VRS_STATE_ESTOP : VRS_STATE_FAULT;
    c->faults |= flag;
    if (c->fault_hinge == 0xFF)
        c->fault_hinge = hinge;
}

void vrs_estop(vrs_core *c)
{
    if (c->state != VRS_STATE_ESTOP)
        fault(c, VRS_FAULT_ESTOP, 0xFF);
}

int vrs_clear_fault(vrs_core *c)
{
    if (c->faults & VRS_FAULT_HARDWARE || c->battery_implausible)
        return VRS_NACK_FAULT_PERSISTS;
    c->state = VRS_STATE_IDLE;
    c->faults = 0;
    c->fault_hinge = 0xFF;
    memcpy(c->targets, c->counts, sizeof c->targets);
    return 0;
}

void vrs_set_reset_reason(vrs_core *c, uint8_t reason) { c->reset_reason = reason; }

int vrs_confirm_zero(vrs_core *c)
{
    uint8_t k;
    if (c->state != VRS_STATE_IDLE)
        return VRS_NACK_BAD_STATE;
    for (k = 0; k < c->cfg.n_hinges; k++) {
        c->zero[k] += c->counts[k];
        c->counts[k] = c->targets[k] = c->pid[k].prev = c->stall_ref[k] = 0;
    }
    c->zero_confirmed = 1;
    return 0;
}

void vrs_mark_zero_confirmed(vrs_core *c) { c->zero_confirmed = 1; }

/* the wiring flags that change what a hinge's counts mean (not VRS_WIRING_DISABLED) */
#define WIRING_COUNTS_FLAGS (VRS_WIRING_ENCODER_REVERSED | VRS_WIRING_MOTOR_REVERSED)

int vrs_set_wiring(vrs_core *c, const vrs_wiring *w)
{
    uint8_t k, seen = 0, driven = 0, moved = 0;
    if (c->state != VRS_STATE_IDLE)
        return VRS_NACK_BAD_STATE;
    for (k = 0; k < c->cfg.n_hinges; k++) {
        if (w->encoder[k] >= c->cfg.n_hinges || (seen & (1u << w->encoder[k]))
            || w->bridge[k] >= c->cfg.n_hinges || (driven & (1u << w->bridge[k]))
            || (w->flags[k] & ~(WIRING_COUNTS_FLAGS | VRS_WIRING_DISABLED)))
            return VRS_NACK_BAD_VALUE;
        seen = (uint8_t)(seen | (1u << w->encoder[k]));
        driven = (uint8_t)(driven | (1u << w->bridge[k]));
        moved |= (uint8_t)(w->encoder[k] != c->wiring.encoder[k] || w->bridge[k] != c->wiring.bridge[k]
                           || (w->flags[k] ^ c->wiring.flags[k]) & WIRING_COUNTS_FLAGS);
    }
    if (memcmp(&c->wiring, w, sizeof *w) != 0) {
        c->wiring = *w;
        c->wiring_changed = 1;
    }
    if (moved) {  /* the counts mean something else now; a hinge disabled or enabled alone keeps the zero */
        c->zero_confirmed = 0;
        memset(c->zero, 0, sizeof c->zero);
    }
    return 0;
}

/* whether hinge k is disabled (VRS_WIRING_DISABLED): braked, never driven */
static int disabled(const vrs_core *c, uint8_t k) { return (c->wiring.flags[k] & VRS_WIRING_DISABLED) != 0; }

uint8_t vrs_get_disabled(const vrs_core *c)
{
    uint8_t k, bits = 0;
    for (k = 0; k < c->cfg.n_hinges; k++)
        if (disabled(c, k))
            bits = (uint8_t)(bits | (1u << k));
    return bits;
}

void vrs_get_wiring(const vrs_core *c, vrs_wiring *out) { *out = c->wiring; }

int vrs_take_wiring_change(vrs_core *c, vrs_wiring *out)
{
    if (!c->wiring_changed)
        return 0;
    c->wiring_changed = 0;
    *out = c->wiring;
    return 1;
}

/* whether no correction is applied (disabled hinges are HELLO's own field) */
static int wiring_is_identity(const vrs_core *c)
{
    uint8_t k;
    for (k = 0; k < c->cfg.n_hinges; k++)
        if (c->wiring.encoder[k] != k || c->wiring.bridge[k] != k || c->wiring.flags[k] & WIRING_COUNTS_FLAGS)
            return 0;
    return 1;
}

/* ---- open-loop programs (PROGRAM; PULSE is one segment): docs/firmware.md, "Open-loop motion" ---------- */

/* |duty| at or above this and the hinge not moving: a program's stall. The duty that drives the motor's
 * continuous current at standstill (continuous / stall current): below it a jammed motor cannot overheat. */
static float program_stall_duty(const vrs_core *c)
{
    return c->cfg.stall_current_ma ? (float)c->cfg.continuous_current_ma / (float)c->cfg.stall_current_ma
                                   : c->cfg.stall_duty;
}

static uint32_t ms_to_ticks(const vrs_core *c, uint32_t ms)
{
    return (ms * c->cfg.loop_rate_hz + 500u) / 1000u;
}

/* start p unless refused (0, or the NACK reason with *detail); max_duty: the largest |duty|, compared in wire units */
static int program_start(vrs_core *c, const vrs_program_spec *p, float max_duty, int need_zero, uint32_t *detail)
{
    vrs_program_run *r = &c->program;
    uint32_t total = 0;
    uint8_t i;
    int32_t at, limit = c->cfg.limit_counts;
    int16_t most = duty_to_wire(max_duty);
    *detail = p->hinge;
    if (c->state != VRS_STATE_IDLE || r->status.end == VRS_PROGRAM_END_RUNNING) {
        *detail = c->state;  /* IDLE (0) here: a program is still running */
        return VRS_NACK_BAD_STATE;
    }
    if (need_zero && !c->zero_confirmed) {
        *detail = 0xFF;
        return VRS_NACK_ZERO_UNCONFIRMED;
    }
    if (p->hinge >= c->cfg.n_hinges || p->n_segments == 0 || p->n_segments > VRS_PROGRAM_MAX_SEGMENTS
        || p->timeout_ms == 0 || p->timeout_ms > VRS_PROGRAM_MAX_MS)
        return VRS_NACK_BAD_VALUE;
    if (disabled(c, p->hinge))
        return VRS_NACK_HINGE_DISABLED;
    if (p->coast >> p->n_segments)  /* a coasting segment past the last */
        return VRS_NACK_BAD_VALUE;
    for (i = 0; i < p->n_segments; i++) {
        int16_t d;
        if (!(p->duty[i] >= -1.0f && p->duty[i] <= 1.0f) || p->ms[i] == 0)  /* NaN too */
            return VRS_NACK_BAD_VALUE;
        if ((p->coast >> i & 1u) && p->duty[i] != 0.0f)  /* a coasting segment drives nothing */
            return VRS_NACK_BAD_VALUE;
        d = duty_to_wire(p->duty[i]);
        if (d > most || d < -most)
            return VRS_NACK_BAD_VALUE;
        total += p->ms[i];
    }
    if (total > VRS_PROGRAM_MAX_MS)
        return VRS_NACK_BAD_VALUE;
    at = c->counts[p->hinge];
    if (p->low >= p->high || p->low < -limit || p->high > limit || at < p->low || at > p->high)
        return VRS_NACK_OUT_OF_RANGE;
    memset(r, 0, sizeof *r);
    r->spec = *p;
    total = 0;
    for (i = 0; i < p->n_segments; i++) {
        r->spec.duty[i] = (float)duty_to_wire(p->duty[i]) / (float)VRS_DUTY_SCALE;  /* as the wire carries it */
        total += p->ms[i];
        r->segment_end[i] = ms_to_ticks(c, total);
    }
    r->timeout_ticks = ms_to_ticks(c, p->timeout_ms);
    for (i = 0; i < VRS_PROGRAM_RATE_TICKS; i++)
        r->history[i] = at;
    r->stall_ref = at;
    r->zero = c->zero[p->hinge];
    r->encoder = c->wiring.encoder[p->hinge];
    r->flags = c->wiring.flags[p->hinge];
    r->bridge = c->wiring.bridge[p->hinge];
    r->status.hinge = p->hinge;
    r->status.end = VRS_PROGRAM_END_RUNNING;
    return 0;
}

int vrs_program(vrs_core *c, const vrs_program_spec *p)
{
    uint32_t detail;
    return program_start(c, p, VRS_PROGRAM_MAX_DUTY, 1, &detail);
}

void vrs_get_program(const vrs_core *c, vrs_program_status *out) { *out = c->program.status; }

static void program_end(vrs_core *c, uint8_t why)
{
    c->program.status.end = why;
    c->program.status.battery_mv = c->battery_mv;
}

/* whether the device is no longer as the program started it: out of IDLE, or its hinge's zero or wiring changed */
static int program_state_changed(const vrs_core *c)
{
    const vrs_program_run *r = &c->program;
    uint8_t h = r->spec.hinge;
    return c->state != VRS_STATE_IDLE || c->zero[h] != r->zero || c->wiring.encoder[h] != r->encoder
           || c->wiring.flags[h] != r->flags || c->wiring.bridge[h] != r->bridge;
}

/* a state change ends the program at once (an ESTOP and a CLEAR_FAULT in one read must not resume it) */
static void program_check_state(vrs_core *c)
{
    if (c->program.status.end == VRS_PROGRAM_END_RUNNING && program_state_changed(c))
        program_end(c, VRS_PROGRAM_END_STATE);
}

/* the start of a tick, the counts read: end the program where it must end, else pick its segment */
static void program_tick(vrs_core *c, uint32_t now_us)
{
    vrs_program_run *r = &c->program;
    uint32_t t = r->status.ticks;
    int32_t at, old;
    int64_t ahead, moved;  /* wide: counts far apart (a glitching encoder) must not overflow */
    float d;
    if (r->status.end != VRS_PROGRAM_END_RUNNING)
        return;
    at = c->counts[r->spec.hinge];
    old = r->history[t % VRS_PROGRAM_RATE_TICKS];  /* VRS_PROGRAM_RATE_TICKS ticks ago (the start before that) */
    r->history[t % VRS_PROGRAM_RATE_TICKS] = at;
    ahead = (int64_t)at
            + ((int64_t)at - old) * (int64_t)ms_to_ticks(c, VRS_PROGRAM_LOOKAHEAD_MS) / VRS_PROGRAM_RATE_TICKS;
    moved = (int64_t)at - r->stall_ref;
    d = c->duty[r->spec.hinge] < 0.0f ? -c->duty[r->spec.hinge] : c->duty[r->spec.hinge];
    if (moved > c->cfg.stall_counts || moved < -c->cfg.stall_counts || d < program_stall_duty(c)) {
        r->stall_ref = at;
        r->stall_since = t;
    }
    if (program_state_changed(c))
        program_end(c, VRS_PROGRAM_END_STATE);
    else if (c->cfg.watchdog_ms && now_us - c->last_rx_us > (uint32_t)c->cfg.watchdog_ms * 1000u)
        program_end(c, VRS_PROGRAM_END_HOST_QUIET);
    else if (at < r->spec.low || at > r->spec.high || ahead < r->spec.low || ahead > r->spec.high)
        program_end(c, VRS_PROGRAM_END_WINDOW);
    else if (t - r->stall_since > ms_to_ticks(c, c->cfg.stall_ms))
        program_end(c, VRS_PROGRAM_END_STALL);
    else if (t >= r->segment_end[r->spec.n_segments - 1])
        program_end(c, VRS_PROGRAM_END_DONE);
    else if (t >= r->timeout_ticks)
        program_end(c, VRS_PROGRAM_END_TIMEOUT);
    else
        while (t >= r->segment_end[r->segment])
            r->segment++;
}

/* the program's duty for hinge k this tick (0: braked, or coasting: program_coasts) */
static float program_duty(const vrs_core *c, uint8_t k)
{
    const vrs_program_run *r = &c->program;
    return r->status.end == VRS_PROGRAM_END_RUNNING && k == r->spec.hinge ? r->spec.duty[r->segment] : 0.0f;
}

/* whether the program coasts hinge k this tick (its segment's windings open); an ended program never does */
static int program_coasts(const vrs_core *c, uint8_t k)
{
    const vrs_program_run *r = &c->program;
    return r->status.end == VRS_PROGRAM_END_RUNNING && k == r->spec.hinge && (r->spec.coast >> r->segment & 1u);
}

/* the end of a tick: its sample (counts read, duty applied) as a PROGRAM_SAMPLE, seq its index */
static void program_sample(vrs_core *c)
{
    vrs_program_run *r = &c->program;
    uint32_t v[2], len;
    uint8_t frame_bytes[32];
    if (r->status.end != VRS_PROGRAM_END_RUNNING)
        return;
    v[0] = (uint32_t)c->counts[r->spec.hinge];
    v[1] = (uint32_t)(int32_t)(program_coasts(c, r->spec.hinge) ? VRS_PROGRAM_COAST
                                                                  : duty_to_wire(c->duty[r->spec.hinge]));
    len = vrs_encode(VRS_MSG_PROGRAM_SAMPLE, (uint16_t)r->status.ticks, v, 0, frame_bytes, sizeof frame_bytes);
    if (!queue(c, frame_bytes, len, VRS_TX_REPLY_RESERVE))
        r->status.dropped++;
    r->status.ticks++;
}

/* PULSE: a one-segment program within the hinge's range, at most VRS_PULSE_MAX_DUTY for VRS_PULSE_MAX_MS; bring-up
 * runs it before the zero is confirmed (the range is then about the counts at the start) */
static int pulse(vrs_core *c, uint8_t hinge, float duty, uint32_t ms, uint32_t *detail)
{
    vrs_program_spec p;
    memset(&p, 0, sizeof p);
    *detail = hinge;
    if (ms > VRS_PULSE_MAX_MS)
        return VRS_NACK_BAD_VALUE;
    p.hinge = hinge;
    p.n_segments = 1;
    p.timeout_ms = (uint16_t)ms;
    p.low = -c->cfg.limit_counts;
    p.high = c->cfg.limit_counts;
    p.duty[0] = duty;
    p.ms[0] = (uint16_t)ms;
    return program_start(c, &p, VRS_PULSE_MAX_DUTY, 0, detail);
}

void vrs_get_heat(const vrs_core *c, float *share_out)
{
    uint8_t k;
    float i_stall = (float)c->cfg.stall_current_ma * 1e-3f, i_cont = (float)c->cfg.continuous_current_ma * 1e-3f;
    float budget = (i_stall * i_stall - i_cont * i_cont) * (float)c->cfg.overload_ms * 1e-3f;
    for (k = 0; k < c->cfg.n_hinges; k++)
        share_out[k] = budget > 0.0f ? c->heat[k] / budget : 0.0f;
}

uint8_t vrs_get_derated(const vrs_core *c) { return c->derated; }

void vrs_hardware_fault(vrs_core *c, uint8_t step, uint8_t hinge)
{
    if (c->setup_error == VRS_SETUP_NONE)
        c->setup_error = step;
    fault(c, VRS_FAULT_HARDWARE, hinge);
}

static int set_targets(vrs_core *c, const int32_t *counts, uint32_t now_us, uint32_t *detail)
{
    uint8_t k, n = c->cfg.n_hinges;
    int32_t far = c->cfg.limit_counts + c->cfg.limit_margin_counts;
    if (c->state == VRS_STATE_ESTOP || c->state == VRS_STATE_FAULT) {
        *detail = c->state;
        return VRS_NACK_BAD_STATE;
    }
    if (!c->zero_confirmed) {
        *detail = 0xFF;
        return VRS_NACK_ZERO_UNCONFIRMED;
    }
    for (k = 0; k < n; k++)
        if (disabled(c, k) ? counts[k] - c->counts[k] > c->cfg.stall_counts
                                 || c->counts[k] - counts[k] > c->cfg.stall_counts
                           : counts[k] > c->cfg.limit_counts || counts[k] < -c->cfg.limit_counts) {
            /* a disabled hinge takes only where it stands (within stall_counts: it is braked there) */
            *detail = k;
            return disabled(c, k) ? VRS_NACK_HINGE_DISABLED : VRS_NACK_OUT_OF_RANGE;
        }
    memcpy(c->targets, counts, n * sizeof counts[0]);
    if (c->state == VRS_STATE_HOLDING)
        c->state = VRS_STATE_ACTIVE;
    if (c->state == VRS_STATE_IDLE) {
        for (k = 0; k < n; k++) {
            c->pid[k].prev = c->counts[k];
            c->pid[k].rate = 0.0f;
            c->pid[k].integral = 0.0f;
            c->stall_ref[k] = c->counts[k];
            c->stall_since_us[k] = now_us;
            c->runaway_sign[k] = 0;
            /* a hinge that sagged past its range may be driven back; LIMIT only if it goes further out */
            c->limit_out[k] = c->counts[k] > far ? c->counts[k] : (c->counts[k] < -far ? -c->counts[k] : far);
        }
        c->state = VRS_STATE_ACTIVE;
    }
    return 0;
}

int vrs_set_targets(vrs_core *c, const int32_t *counts, uint32_t now_us)
{
    uint32_t detail;
    c->now_us = now_us;
    return set_targets(c, counts, now_us, &detail);
}

/* g for hinge (VRS_BROADCAST: all), its bounds already checked */
static int store_gains(vrs_core *c, uint8_t hinge, const vrs_gains *g)
{
    uint8_t k;
    if (hinge != VRS_BROADCAST && hinge >= c->cfg.n_hinges)
        return VRS_NACK_BAD_VALUE;
    for (k = 0; k < c->cfg.n_hinges; k++)
        if (hinge == VRS_BROADCAST || hinge == k) {
            c->gains[k] = *g;
            c->alpha[k] = vrs_pid_alpha(g->cutoff_hz, c->dt);
        }
    return 0;
}

int vrs_set_gains(vrs_core *c, uint8_t hinge, const vrs_gains *g)
{
    return gains_valid(g) ? store_gains(c, hinge, g) : VRS_NACK_BAD_VALUE;
}

int vrs_set_telemetry_rate(vrs_core *c, uint16_t rate_hz)
{
    if (rate_hz > c->cfg.max_telemetry_hz)
        return VRS_NACK_BAD_VALUE;
    c->telemetry_every = rate_hz == 0 ? 0 : (uint16_t)((c->cfg.loop_rate_hz + rate_hz / 2) / rate_hz);
    if (rate_hz && c->telemetry_every == 0)
        c->telemetry_every = 1;
    return 0;
}

int vrs_init(vrs_core *c, const vrs_config *cfg, const vrs_gains *gains, const int32_t *counts_now)
{
    uint8_t k;
    memset(c, 0, sizeof *c);
    if (cfg->n_hinges == 0 || cfg->n_hinges > VRS_MAX_HINGES || cfg->loop_rate_hz == 0)
        return -1;
    c->cfg = *cfg;
    c->dt = 1.0f / (float)cfg->loop_rate_hz;
    for (k = 0; k < cfg->n_hinges; k++) {
        if (vrs_set_gains(c, k, &gains[k]) != 0)
            return -1;
        c->counts[k] = c->targets[k] = c->pid[k].prev = c->stall_ref[k] = counts_now[k];
        c->limit_out[k] = cfg->limit_counts + cfg->limit_margin_counts;
        c->wiring.encoder[k] = c->wiring.bridge[k] = k;
    }
    c->program.status.hinge = 0xFF;
    c->state = VRS_STATE_IDLE;
    c->fault_hinge = 0xFF;
    return 0;
}

/* ---- commands ------------------------------------------------------------------------- */

/* state, faults, fault_hinge: three body values, as STATE and TELEMETRY carry them */
static void put_status(const vrs_core *c, uint32_t *v)
{
    v[0] = c->state;
    v[1] = c->faults;
    v[2] = c->fault_hinge;
}

/* counts then targets: two per-hinge arrays, as STATE and TELEMETRY carry them */
static void put_positions(const vrs_core *c, uint32_t *v)
{
    uint8_t k, n = c->cfg.n_hinges;
    for (k = 0; k < n; k++) {
        v[k] = (uint32_t)c->counts[k];
        v[n + k] = (uint32_t)c->targets[k];
    }
}

static void gains_to_wire(const vrs_gains *g, uint32_t *v)
{
    v[0] = round_to_u32(g->kp * (float)VRS_GAIN_SCALE);
    v[1] = round_to_u32(g->ki * (float)VRS_GAIN_SCALE);
    v[2] = round_to_u32(g->kd * (float)VRS_GAIN_SCALE);
    v[3] = round_to_u32(g->cutoff_hz * (float)VRS_CUTOFF_SCALE);
    v[4] = round_to_u32(g->integral_limit * (float)VRS_DUTY_SCALE);
    v[5] = round_to_u32(g->deadband * (float)VRS_DUTY_SCALE);
    v[6] = g->hold_band;
}

static void gains_from_wire(const uint32_t *v, vrs_gains *g)
{
    g->kp = (float)(int32_t)v[0] / (float)VRS_GAIN_SCALE;
    g->ki = (float)(int32_t)v[1] / (float)VRS_GAIN_SCALE;
    g->kd = (float)(int32_t)v[2] / (float)VRS_GAIN_SCALE;
    g->cutoff_hz = (float)v[3] / (float)VRS_CUTOFF_SCALE;
    g->integral_limit = (float)v[4] / (float)VRS_DUTY_SCALE;
    g->deadband = (float)v[5] / (float)VRS_DUTY_SCALE;
    g->hold_band = (uint16_t)v[6];
}

static void execute(vrs_core *c, uint8_t id, uint16_t seq, uint16_t crc, const uint32_t *v, uint8_t n)
{
    uint32_t out[VRS_MAX_FIELDS], detail = 0;
    int32_t targets[VRS_MAX_HINGES];
    vrs_gains g;
    uint8_t k, nh = c->cfg.n_hinges;
    int r;
    switch (id) {
    case VRS_MSG_HEARTBEAT:
        return;
    case VRS_MSG_HELLO:
        out[0] = c->cfg.fw_version[0];
        out[1] = c->cfg.fw_version[1];
        out[2] = c->cfg.fw_version[2];
        out[3] = VRS_PROTOCOL_VERSION;
        out[4] = nh;
        out[5] = c->cfg.loop_rate_hz;
        out[6] = c->cfg.watchdog_ms;
        out[7] = c->cfg.max_telemetry_hz;
        out[8] = c->reset_reason;
        out[9] = c->setup_error;
        out[10] = c->zero_confirmed;
        out[11] = (uint32_t)!wiring_is_identity(c);
        out[12] = vrs_get_disabled(c);
        memset(c->replies, 0, sizeof c->replies);  /* a new session: its seqs start again */
        reply(c, id, seq, crc, VRS_MSG_HELLO_REPLY, out, 0);
        return;
    case VRS_MSG_GET_STATE:
        out[0] = c->cfg.fw_version[0];
        out[1] = c->cfg.fw_version[1];
        out[2] = c->cfg.fw_version[2];
        put_status(c, out + 3);
        out[6] = c->now_us;
        out[7] = c->rx_bad_frames;
        out[8] = c->zero_confirmed;
        out[9] = c->derated;
        out[10] = vrs_get_disabled(c);
        put_positions(c, out + 11);
        for (k = 0; k < nh; k++)  /* what the PID holds a load with, hidden at rest (its duty is off) */
            out[11 + 2 * nh + k] = (uint32_t)(int32_t)duty_to_wire(c->pid[k].integral);
        reply(c, id, seq, crc, VRS_MSG_STATE, out, nh);
        return;
    case VRS_MSG_SET_TARGETS:
        if (n != nh) {
            nack(c, seq, crc, id, VRS_NACK_BAD_LENGTH, n);
            return;
        }
        for (k = 0; k < nh; k++)
            targets[k] = (int32_t)v[k];
        r = set_targets(c, targets, c->now_us, &detail);
        break;
    case VRS_MSG_SET_GAINS:
        gains_from_wire(v + 1, &g);
        detail = v[0];
        r = wire_gains_valid(v + 1) ? store_gains(c, (uint8_t)v[0], &g) : VRS_NACK_BAD_VALUE;
        break;
    case VRS_MSG_GET_GAINS:
        if (v[0] >= nh) {
            nack(c, seq, crc, id, VRS_NACK_BAD_VALUE, v[0]);
            return;
        }
        out[0] = v[0];
        gains_to_wire(&c->gains[v[0]], out + 1);
        reply(c, id, seq, crc, VRS_MSG_GAINS, out, 0);
        return;
    case VRS_MSG_ESTOP:
        vrs_estop(c);
        r = 0;
        break;
    case VRS_MSG_CLEAR_FAULT:
        r = vrs_clear_fault(c);
        detail = c->faults;
        break;
    case VRS_MSG_CONFIRM_ZERO:
        r = vrs_confirm_zero(c);
        detail = c->state;
        break;
    case VRS_MSG_PULSE:
        r = pulse(c, (uint8_t)v[0], (float)(int16_t)v[1] / (float)VRS_DUTY_SCALE, v[2], &detail);
        break;
    case VRS_MSG_PROGRAM: {
        vrs_program_spec p;
        memset(&p, 0, sizeof p);
        p.hinge = (uint8_t)v[0];
        p.low = (int32_t)v[1];
        p.high = (int32_t)v[2];
        p.timeout_ms = (uint16_t)v[3];
        p.n_segments = (uint8_t)v[4];
        for (k = 0; k < VRS_PROGRAM_MAX_SEGMENTS; k++) {
            if ((int32_t)v[5 + k] == VRS_PROGRAM_COAST)  /* outside +-VRS_DUTY_SCALE: no duty, the segment coasts */
                p.coast = (uint16_t)(p.coast | 1u << k);
            else
                p.duty[k] = (float)(int32_t)v[5 + k] / (float)VRS_DUTY_SCALE;
            p.ms[k] = (uint16_t)v[5 + VRS_PROGRAM_MAX_SEGMENTS + k];
        }
        r = program_start(c, &p, VRS_PROGRAM_MAX_DUTY, 1, &detail);
        break;
    }
    case VRS_MSG_GET_PROGRAM: {
        const vrs_program_status *st = &c->program.status;
        out[0] = st->hinge;
        out[1] = st->end;
        out[2] = st->ticks;
        out[3] = st->dropped;
        out[4] = st->battery_mv;
        out[5] = st->hinge < nh ? (uint32_t)c->counts[st->hinge] : 0u;
        reply(c, id, seq, crc, VRS_MSG_PROGRAM_STATUS, out, 0);
        return;
    }
    case VRS_MSG_SET_WIRING: {
        vrs_wiring w;
        if (n != nh) {
            nack(c, seq, crc, id, VRS_NACK_BAD_LENGTH, n);
            return;
        }
        memset(&w, 0, sizeof w);
        for (k = 0; k < nh; k++) {
            w.encoder[k] = (uint8_t)v[k];
            w.flags[k] = (uint8_t)v[nh + k];
            w.bridge[k] = (uint8_t)v[2 * nh + k];
        }
        r = vrs_set_wiring(c, &w);
        break;
    }
    case VRS_MSG_GET_WIRING:
        for (k = 0; k < nh; k++) {
            out[k] = c->wiring.encoder[k];
            out[nh + k] = c->wiring.flags[k];
            out[2 * nh + k] = c->wiring.bridge[k];
        }
        reply(c, id, seq, crc, VRS_MSG_WIRING, out, nh);
        return;
    case VRS_MSG_SET_TELEMETRY_RATE:
        r = vrs_set_telemetry_rate(c, (uint16_t)v[0]);
        break;
    default: /* a device -> host message sent to the device */
        r = VRS_NACK_UNKNOWN_MESSAGE;
        break;
    }
    if (r)
        nack(c, seq, crc, id, r, detail);
    else
        ack(c, seq, crc, id);
}

static void frame(vrs_core *c, const uint8_t *bytes, uint32_t len)
{
    uint32_t values[VRS_MAX_FIELDS];
    uint16_t seq, crc;
    uint8_t id, n, i;
    int r = vrs_decode(bytes, len, &id, &seq, values, &n);
    if (r < 0) {
        c->rx_bad_frames++;
        return;
    }
    crc = vrs_crc16(bytes, len);
    if (r == VRS_NACK_BAD_VERSION) {  /* not our protocol: answered, but it does not feed the watchdog */
        nack(c, seq, crc, id, r, VRS_PROTOCOL_VERSION);
        return;
    }
    c->rx_good_frames++;
    c->last_rx_us = c->now_us;
    if (c->state == VRS_STATE_HOLDING)  /* the host is back before the hold ran out */
        c->state = VRS_STATE_ACTIVE;
    for (i = 0; i < VRS_REPLY_MEMORY && id != VRS_MSG_ESTOP; i++) {  /* an ESTOP always runs */
        const vrs_reply *m = &c->replies[i];
        if (m->used && m->seq == seq && m->request_crc == crc && c->now_us - m->at_us < VRS_REPLY_KEEP_US) {
            /* a repeat: the original answer, and nothing run again */
            queue(c, m->payload, m->len, 0);
            return;
        }
    }
    if (r)
        nack(c, seq, crc, id, r, n);
    else
        execute(c, id, seq, crc, values, n);
}

void vrs_rx(vrs_core *c, const uint8_t *bytes, uint32_t n, uint32_t now_us)
{
    uint32_t i;
    c->now_us = now_us;
    for (i = 0; i < n; i++) {
        if (bytes[i] != 0) {
            if (c->rx_overflow)
                continue;
            if (c->rx_len < VRS_RX_CAP)
                c->rx_buf[c->rx_len++] = bytes[i];
            else {
                c->rx_overflow = 1;
                c->rx_len = 0;
            }
            continue;
        }
        if (c->rx_overflow)
            c->rx_bad_frames++;
        else if (c->rx_len) {
            frame(c, c->rx_buf, c->rx_len);
            program_check_state(c);
        }
        c->rx_overflow = 0;
        c->rx_len = 0;
    }
}

/* ---- the control tick ------------------------------------------------------------------ */

/* counts a runaway moves against its duty in a window of a tenth of stall_ms (30 ms on the spec): a reversed
 * encoder or motor moved 20-45 on the twin; a flap sagging braked against motors too weak to hold it, at most 9 */
#define RUNAWAY_COUNTS 16

/* |duty| the I2t protection holds a derated hinge to: the continuous rating over the stall current */
static float derated_cap(const vrs_core *c)
{
    return c->cfg.stall_current_ma ? (float)c->cfg.continuous_current_ma / (float)c->cfg.stall_current_ma : 1.0f;
}

/* |duty| at or above which STALL and RUNAWAY watch hinge k: a derated hinge's duty is held to the cap, so the
 * same share of what it may give */
static float stall_duty_of(const vrs_core *c, uint8_t k)
{
    return c->derated & (1u << k) ? c->cfg.stall_duty * derated_cap(c) : c->cfg.stall_duty;
}

static void checks(vrs_core *c, uint32_t now_us)
{
    uint8_t k, n = c->cfg.n_hinges;
    int32_t far = c->cfg.limit_counts + c->cfg.limit_margin_counts;
    if (c->state == VRS_STATE_ACTIVE && c->cfg.watchdog_ms
        && now_us - c->last_rx_us > (uint32_t)c->cfg.watchdog_ms * 1000u) {
        c->state = VRS_STATE_HOLDING;  /* the host went quiet: hold the last targets, then release */
        c->away_since_us = now_us;
    }
    if (c->state == VRS_STATE_HOLDING && now_us - c->away_since_us >= (uint32_t)c->cfg.host_away_hold_ms * 1000u) {
        fault(c, VRS_FAULT_WATCHDOG, 0xFF);
        return;
    }
    for (k = 0; k < n; k++) {
        int32_t out = c->counts[k] < 0 ? -c->counts[k] : c->counts[k];
        if (disabled(c, k))  /* braked, never driven: where it sags (or a dead encoder says) stops no other */
            continue;
        if (out > c->limit_out[k]) {
            fault(c, VRS_FAULT_LIMIT, k);
            return;
        }
        if (out + c->cfg.limit_margin_counts < c->limit_out[k])  /* back toward the range: the limit follows */
            c->limit_out[k] = out + c->cfg.limit_margin_counts > far ? out + c->cfg.limit_margin_counts : far;
    }
    if (c->cfg.overcurrent_ma > 0)
        for (k = 0; k < n; k++)
            if (c->current_ma[k] > c->cfg.overcurrent_ma || c->current_ma[k] < -c->cfg.overcurrent_ma) {
                fault(c, VRS_FAULT_OVERCURRENT, k);
                return;
            }
    for (k = 0; k < n; k++) {
        int32_t moved = c->counts[k] - c->stall_ref[k];
        float d = c->duty[k] < 0.0f ? -c->duty[k] : c->duty[k];
        if (moved > c->cfg.stall_counts || moved < -c->cfg.stall_counts || d < stall_duty_of(c, k)) {
            c->stall_ref[k] = c->counts[k];
            c->stall_since_us[k] = now_us;
        }
    }
    for (k = 0; k < n; k++)
        if (now_us - c->stall_since_us[k] > (uint32_t)c->cfg.stall_ms * 1000u) {
            fault(c, VRS_FAULT_STALL, k);
            return;
        }
    /* RUNAWAY: a duty of one sign at or above the stall duty, and the hinge moving the other way by more than
     * RUNAWAY_COUNTS in each of three windows of a tenth of stall_ms, each no slower than the one before (a
     * reversed encoder or motor: the PID drives it away ever faster). A hinge braking an overshoot moves
     * against its duty too, but slower and slower; one flung back by flaps meeting, for a window or two; a flap
     * sagging against a motor too weak to hold it, slowly. Faults within three windows (90 ms on the spec) of
     * the duty reaching the stall duty and the hinge its runaway speed. */
    for (k = 0; k < n; k++) {
        float d = c->duty[k] < 0.0f ? -c->duty[k] : c->duty[k];
        int8_t sign = d < stall_duty_of(c, k) ? 0 : (c->duty[k] > 0.0f ? 1 : -1);
        int32_t against = (c->runaway_ref[k] - c->counts[k]) * c->runaway_sign[k];
        if (sign == 0 || sign != c->runaway_sign[k]) {
            c->runaway_sign[k] = sign;
            c->runaway_before[k] = 0;
            c->runaway_windows[k] = 0;
        } else if (now_us - c->runaway_since_us[k] < (uint32_t)c->cfg.stall_ms * 100u) {
            continue;
        } else {
            c->runaway_windows[k] = against > RUNAWAY_COUNTS && against >= c->runaway_before[k]
                                        ? (uint8_t)(c->runaway_windows[k] + 1) : 0;
            c->runaway_before[k] = against;
            if (c->runaway_windows[k] >= 3) {
                fault(c, VRS_FAULT_RUNAWAY, k);
                return;
            }
        }
        c->runaway_ref[k] = c->counts[k];
        c->runaway_since_us[k] = now_us;
    }
}

static void telemetry(vrs_core *c)
{
    uint32_t v[VRS_MAX_FIELDS];
    uint8_t frame_bytes[VRS_MAX_PAYLOAD];
    uint8_t k, n = c->cfg.n_hinges;
    uint32_t len;
    v[0] = c->now_us;
    put_status(c, v + 1);
    put_positions(c, v + 4);
    for (k = 0; k < n; k++) {
        v[4 + 2 * n + k] = (uint32_t)(int32_t)duty_to_wire(c->duty[k]);
        v[4 + 3 * n + k] = (uint32_t)(int32_t)c->current_ma[k];
    }
    len = vrs_encode(VRS_MSG_TELEMETRY, c->telemetry_seq, v, n, frame_bytes, sizeof frame_bytes);
    if (!queue(c, frame_bytes, len, VRS_TX_REPLY_RESERVE))
        c->telemetry_dropped++;
    c->telemetry_seq++;
}

void vrs_tick(vrs_core *c, uint32_t now_us, const int32_t *counts, const int16_t *current_ma,
              float *duty_out, uint8_t *decay_out)
{
    uint8_t k, n = c->cfg.n_hinges;
    int driving;
    float i_stall = (float)c->cfg.stall_current_ma * 1e-3f, i_cont = (float)c->cfg.continuous_current_ma * 1e-3f;
    float budget = (i_stall * i_stall - i_cont * i_cont) * (float)c->cfg.overload_ms * 1e-3f;
    float cap = derated_cap(c);
    c->now_us = now_us;
    for (k = 0; k < n; k++) {
        int32_t raw = counts[c->wiring.encoder[k]];
        c->counts[k] = (c->wiring.flags[k] & VRS_WIRING_ENCODER_REVERSED ? -raw : raw) - c->zero[k];
        c->current_ma[k] = current_ma ? current_ma[c->wiring.bridge[k]] : 0;
    }
    program_tick(c, now_us);
    if (c->state == VRS_STATE_ACTIVE || c->state == VRS_STATE_HOLDING)
        checks(c, now_us);
    driving = c->state == VRS_STATE_ACTIVE || c->state == VRS_STATE_HOLDING;
    for (k = 0; k < n; k++) {
        float i;
        if (driving && !disabled(c, k))
            c->duty[k] = vrs_pid_update(&c->pid[k], &c->gains[k], c->alpha[k], c->dt, c->targets[k], c->counts[k]);
        else if (disabled(c, k)) {  /* braked in every state; its target is where it stands */
            c->duty[k] = 0.0f;
            c->targets[k] = c->pid[k].prev = c->counts[k];
            c->pid[k].rate = c->pid[k].integral = 0.0f;
        } else {
            c->duty[k] = program_duty(c, k);
            c->pid[k].prev = c->counts[k];
        }
        /* I2t: current estimated from duty at standstill (an upper bound); over budget, the continuous rating */
        if (budget > 0.0f) {
            if (c->derated & (1u << k))
                c->duty[k] = c->duty[k] > cap ? cap : (c->duty[k] < -cap ? -cap : c->duty[k]);
            i = c->duty[k] * i_stall;
            c->heat[k] += (i * i - i_cont * i_cont) * c->dt;
            if (c->heat[k] < 0.0f)
                c->heat[k] = 0.0f;
            if (c->heat[k] >= budget)
                c->derated = (uint8_t)(c->derated | (1u << k));
            else if (c->heat[k] < 0.5f * budget)
                c->derated = (uint8_t)(c->derated & ~(1u << k));
        }
        duty_out[c->wiring.bridge[k]] = c->wiring.flags[k] & VRS_WIRING_MOTOR_REVERSED ? -c->duty[k]
                                                                                   : c->duty[k];
        /* brake (slow decay) in every state, IDLE too: duty proportional to voltage while driving, and
         * at zero duty the flaps hold where they stopped (a coasting device held by its root flap folds
         * within 0.5 s: docs/firmware.md); only a program's coasting segment opens the windings, and its
         * every end (window, timeout, quiet host, state change) brakes again */
        decay_out[c->wiring.bridge[k]] = program_coasts(c, k) ? VRS_DECAY_COAST : VRS_DECAY_BRAKE;
    }
    program_sample(c);
    if (c->telemetry_every && c->ticks % c->telemetry_every == 0)
        telemetry(c);
    c->ticks++;
}

/* ---- battery compensation -------------------------------------------------------------- */

void vrs_set_battery_mv(vrs_core *c, uint16_t mv) { c->battery_mv = mv; }

void vrs_set_battery_plausible(vrs_core *c, int plausible)
{
    c->battery_implausible = (uint8_t)!plausible;
    if (!plausible && !(c->faults & VRS_FAULT_BATTERY))
        fault(c, VRS_FAULT_BATTERY, 0xFF);
}

void vrs_pwm(const vrs_core *c, float *pwm_out)
{
    uint8_t k, n = c->cfg.n_hinges;
    float scale = c->battery_mv ? (float)c->cfg.drive_cap_mv / (float)c->battery_mv : 1.0f;
    for (k = 0; k < n; k++) {
        float p = c->duty[k] * scale;
        if (c->wiring.flags[k] & VRS_WIRING_MOTOR_REVERSED)
            p = -p;
        pwm_out[c->wiring.bridge[k]] = p > 1.0f ? 1.0f : (p < -1.0f ? -1.0f : p);
    }
}

/* ---- accessors ------------------------------------------------------------------------- */

size_t vrs_core_size(void) { return sizeof(vrs_core); }
uint8_t vrs_get_state(const vrs_core *c) { return c->state; }
uint16_t vrs_get_faults(const vrs_core *c) { return c->faults; }
uint8_t vrs_get_fault_hinge(const vrs_core *c) { return c->fault_hinge; }
uint32_t vrs_get_rx_bad_frames(const vrs_core *c) { return c->rx_bad_frames; }
uint32_t vrs_get_telemetry_dropped(const vrs_core *c) { return c->telemetry_dropped; }
uint16_t vrs_get_battery_mv(const vrs_core *c) { return c->battery_mv; }

void vrs_get_targets(const vrs_core *c, int32_t *out) { memcpy(out, c->targets, c->cfg.n_hinges * sizeof out[0]); }

int vrs_get_gains(const vrs_core *c, uint8_t hinge, vrs_gains *out)
{
    if (hinge >= c->cfg.n_hinges)
        return VRS_NACK_BAD_VALUE;
    *out = c->gains[hinge];
    return 0;
}

vrs_pid *vrs_pid_memory(vrs_core *c)
{
    return c->pid;
}

/* ---- through the hardware-access struct ----------------------------------------------- */

void vrs_service(vrs_core *c, const vrs_hw *hw)
{
    uint8_t buf[64];
    int got, room;
    uint32_t n;
    while ((got = hw->serial_read(hw->ctx, buf, (int)sizeof buf)) > 0)
        vrs_rx(c, buf, (uint32_t)got, hw->micros(hw->ctx));
    room = hw->serial_room(hw->ctx);
    while (room > 0 && (n = vrs_tx(c, buf, room < (int)sizeof buf ? (uint32_t)room : sizeof buf)) > 0) {
        hw->serial_write(hw->ctx, buf, (int)n);
        room -= (int)n;
    }
}

void vrs_control(vrs_core *c, const vrs_hw *hw)
{
    int32_t counts[VRS_MAX_HINGES];
    int16_t current[VRS_MAX_HINGES];
    float duty[VRS_MAX_HINGES], pwm[VRS_MAX_HINGES];
    uint8_t decay[VRS_MAX_HINGES];
    uint16_t mv;
    int sensed = hw->read_current_ma != NULL && hw->read_current_ma(hw->ctx, current) == 0;
    hw->read_counts(hw->ctx, counts);
    if (hw->read_battery_mv != NULL && hw->read_battery_mv(hw->ctx, &mv) == 0)
        vrs_set_battery_mv(c, mv);
    vrs_tick(c, hw->micros(hw->ctx), counts, sensed ? current : NULL, duty, decay);
    vrs_pwm(c, pwm);
    hw->write_drive(hw->ctx, pwm, decay);
}
