/* The firmware PID (docs/protocol.md; the same law controllers/pid.py stated in float64), in float.
 *
 * Per hinge and tick (dt = 1 / loop rate):
 *   e     = target - counts
 *   rate  = rate + alpha * ((counts - prev) / dt - rate)      derivative on measurement, filtered
 *   I     = clamp(I + ki * e * dt, +-integral_limit)          frozen when |e| <= hold_band, or when
 *                                                             the output is saturated the same way
 *   u     = kp * e + I - kd * rate
 *   duty  = sign(u) * (deadband + (1 - deadband) * |u|)       off when |e| <= hold_band
 *   duty  = clamp(duty, -1, 1)
 */
#include "vrs_core.h"

static float absf(float x) { return x < 0.0f ? -x : x; }
static float clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

float vrs_pid_alpha(float cutoff_hz, float dt)
{
    float tau = 1.0f / (6.28318530718f * cutoff_hz);
    return dt / (dt + tau);
}

float vrs_pid_update(vrs_pid *s, const vrs_gains *g, float alpha, float dt, int32_t target, int32_t counts)
{
    float e = (float)((int64_t)target - counts);
    float u_free, u;
    int on_target = absf(e) <= (float)g->hold_band;
    s->rate += alpha * ((float)((int64_t)counts - s->prev) / dt - s->rate);
    s->prev = counts;
    u_free = g->kp * e + s->integral - g->kd * s->rate;
    if (!on_target && !(absf(u_free) >= 1.0f && u_free * e > 0.0f))
        s->integral = clampf(s->integral + g->ki * e * dt, -g->integral_limit, g->integral_limit);
    u = g->kp * e + s->integral - g->kd * s->rate;
    if (!on_target && u != 0.0f) {
        float mag = g->deadband + (1.0f - g->deadband) * absf(u);
        u = u > 0.0f ? mag : -mag;
    }
    return clampf(u, -1.0f, 1.0f);
}
