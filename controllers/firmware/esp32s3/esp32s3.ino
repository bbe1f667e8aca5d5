/* VRScroll firmware for the ESP32-S3 (Arduino core 3.x): the hardware-access struct of the
 * portable core (controllers/firmware/vrs_core.h) and nothing else. Every decision (protocol,
 * states, watchdog, faults, PID) is the core's; this file reads encoders and the battery, drives
 * six DRV8833 H-bridges, keeps the 1 kHz tick and moves serial bytes. docs/firmware.md has the
 * wiring, the build commands and the bring-up. */
#include <Arduino.h>
#include <driver/pulse_cnt.h>

#include "pins.h"
#include "vrs_core.h"

static vrs_core core;
static pcnt_unit_handle_t pcnt[N_PCNT_HINGES];
static volatile int32_t soft_counts[6];        /* hinges N_PCNT_HINGES.. : decoded in the interrupt */
static volatile uint8_t soft_state[6];
static volatile uint32_t ticks_due;             /* written by the timer interrupt only */
static uint32_t ticks_done;                    /* written by loop() only */
static int8_t drive_dir[6];                    /* which input carries the PWM: +1 IN2, -1 IN1, 0 none */
static hw_timer_t *timer;

/* ---- encoders ----------------------------------------------------------------------------------- */

static void pcnt_setup(int k)
{
    pcnt_unit_config_t unit = {};
    unit.low_limit = -32768;
    unit.high_limit = 32767;
    unit.flags.accum_count = 1;  /* the driver extends the 16-bit counter on overflow */
    pcnt_new_unit(&unit, &pcnt[k]);
    pcnt_glitch_filter_config_t filter = {.max_glitch_ns = 1000};
    pcnt_unit_set_glitch_filter(pcnt[k], &filter);
    pcnt_chan_config_t a = {.edge_gpio_num = PIN_ENC_A[k], .level_gpio_num = PIN_ENC_B[k]};
    pcnt_chan_config_t b = {.edge_gpio_num = PIN_ENC_B[k], .level_gpio_num = PIN_ENC_A[k]};
    pcnt_channel_handle_t ca, cb;
    pcnt_new_channel(pcnt[k], &a, &ca);
    pcnt_new_channel(pcnt[k], &b, &cb);
    /* x4 quadrature: every edge of A and of B counts, its sign from the other channel's level */
    pcnt_channel_set_edge_action(ca, PCNT_CHANNEL_EDGE_ACTION_DECREASE, PCNT_CHANNEL_EDGE_ACTION_INCREASE);
    pcnt_channel_set_level_action(ca, PCNT_CHANNEL_LEVEL_ACTION_KEEP, PCNT_CHANNEL_LEVEL_ACTION_INVERSE);
    pcnt_channel_set_edge_action(cb, PCNT_CHANNEL_EDGE_ACTION_INCREASE, PCNT_CHANNEL_EDGE_ACTION_DECREASE);
    pcnt_channel_set_level_action(cb, PCNT_CHANNEL_LEVEL_ACTION_KEEP, PCNT_CHANNEL_LEVEL_ACTION_INVERSE);
    pcnt_unit_add_watch_point(pcnt[k], unit.low_limit);
    pcnt_unit_add_watch_point(pcnt[k], unit.high_limit);
    pcnt_unit_enable(pcnt[k]);
    pcnt_unit_clear_count(pcnt[k]);
    pcnt_unit_start(pcnt[k]);
}

/* Gray-code step: +1, -1 or 0 for (previous AB, new AB) */
static const int8_t QUAD_STEP[16] = {0, 1, -1, 0, -1, 0, 0, 1, 1, 0, 0, -1, 0, -1, 1, 0};

static void IRAM_ATTR soft_encoder(void *arg)
{
    int k = (int)(intptr_t)arg;
    uint8_t ab = (uint8_t)(digitalRead(PIN_ENC_A[k]) << 1 | digitalRead(PIN_ENC_B[k]));
    soft_counts[k] += QUAD_STEP[soft_state[k] << 2 | ab];
    soft_state[k] = ab;
}

static void read_counts(void *ctx, int32_t *counts)
{
    (void)ctx;
    for (int k = 0; k < 6; k++) {
        if (k < N_PCNT_HINGES) {
            int c = 0;
            pcnt_unit_get_count(pcnt[k], &c);
            counts[k] = c;
        } else {
            counts[k] = soft_counts[k];
        }
    }
}

/* ---- motors ------------------------------------------------------------------------------------- */

/* DRV8833: IN1 IN2 = 1 0 forward, 0 1 reverse, 1 1 brake, 0 0 coast. Slow decay (brake in the
 * off-time) keeps one input high and puts the PWM, inverted, on the other; fast decay (coast in the
 * off-time) keeps one input low and puts the PWM on the other. */
static void write_drive(void *ctx, const float *pwm, const uint8_t *decay)
{
    (void)ctx;
    const uint32_t full = (1u << PWM_BITS) - 1;
    for (int k = 0; k < 6; k++) {
        int8_t dir = pwm[k] > 0.0f ? 1 : (pwm[k] < 0.0f ? -1 : 0);
        int pwm_pin = dir > 0 ? PIN_IN2[k] : PIN_IN1[k];
        int fixed_pin = dir > 0 ? PIN_IN1[k] : PIN_IN2[k];
        if (dir != drive_dir[k]) {
            if (drive_dir[k] != 0)
                ledcDetach(drive_dir[k] > 0 ? PIN_IN2[k] : PIN_IN1[k]);
            if (dir != 0)
                ledcAttachChannel(pwm_pin, PWM_HZ, PWM_BITS, PWM_FIRST_CHANNEL + k);
            drive_dir[k] = dir;
        }
        if (dir == 0) {
            uint8_t level = decay[k] == VRS_DECAY_BRAKE ? HIGH : LOW;
            pinMode(PIN_IN1[k], OUTPUT);
            pinMode(PIN_IN2[k], OUTPUT);
            digitalWrite(PIN_IN1[k], level);
            digitalWrite(PIN_IN2[k], level);
            continue;
        }
        float mag = pwm[k] > 0.0f ? pwm[k] : -pwm[k];
        uint32_t on = (uint32_t)(mag * (float)full + 0.5f);
        pinMode(fixed_pin, OUTPUT);
        if (decay[k] == VRS_DECAY_BRAKE) {
            digitalWrite(fixed_pin, HIGH);
            ledcWrite(pwm_pin, full - on);   /* low while driving, high (brake) in the off-time */
        } else {
            digitalWrite(fixed_pin, LOW);
            ledcWrite(pwm_pin, on);          /* high while driving, low (coast) in the off-time */
        }
    }
}

/* ---- clock, serial, battery --------------------------------------------------------------------- */

static uint32_t micros_now(void *ctx) { (void)ctx; return (uint32_t)micros(); }

static int serial_read(void *ctx, uint8_t *buf, int max)
{
    (void)ctx;
    int n = Serial.available();
    return n > 0 ? (int)Serial.readBytes(buf, n < max ? n : max) : 0;
}

static void serial_write(void *ctx, const uint8_t *buf, int n) { (void)ctx; Serial.write(buf, (size_t)n); }

static int read_battery_mv(void *ctx, uint16_t *mv)
{
    (void)ctx;
    *mv = (uint16_t)(analogReadMilliVolts(PIN_BATTERY) * BATTERY_DIVIDER);
    return 0;
}

static const vrs_hw hw = {NULL, micros_now, read_counts, write_drive, serial_read, serial_write,
                          NULL /* the DRV8833 reports no current */, read_battery_mv};

static void IRAM_ATTR on_timer() { ticks_due++; }

void setup()
{
    Serial.begin(921600);  /* USB CDC: the rate is ignored */
    for (int k = 0; k < 6; k++) {
        pinMode(PIN_IN1[k], OUTPUT);
        pinMode(PIN_IN2[k], OUTPUT);
        digitalWrite(PIN_IN1[k], LOW);
        digitalWrite(PIN_IN2[k], LOW);
        pinMode(PIN_ENC_A[k], INPUT_PULLUP);
        pinMode(PIN_ENC_B[k], INPUT_PULLUP);
        if (k < N_PCNT_HINGES) {
            pcnt_setup(k);
        } else {
            soft_state[k] = (uint8_t)(digitalRead(PIN_ENC_A[k]) << 1 | digitalRead(PIN_ENC_B[k]));
            attachInterruptArg(PIN_ENC_A[k], soft_encoder, (void *)(intptr_t)k, CHANGE);
            attachInterruptArg(PIN_ENC_B[k], soft_encoder, (void *)(intptr_t)k, CHANGE);
        }
    }
    analogSetPinAttenuation(PIN_BATTERY, ADC_11db);

    vrs_config cfg = {VRS_DEVICE_N_HINGES, VRS_DEVICE_LOOP_RATE_HZ, VRS_DEVICE_WATCHDOG_MS,
                      VRS_DEVICE_MAX_TELEMETRY_HZ, VRS_DEVICE_LIMIT_COUNTS, VRS_DEVICE_LIMIT_MARGIN_COUNTS,
                      VRS_DEVICE_STALL_DUTY, VRS_DEVICE_STALL_COUNTS, VRS_DEVICE_STALL_MS, VRS_DEVICE_OVERCURRENT_MA,
                      VRS_DEVICE_DRIVE_CAP_MV,
                      {VRS_DEVICE_FW_VERSION_MAJOR, VRS_DEVICE_FW_VERSION_MINOR, VRS_DEVICE_FW_VERSION_PATCH}};
    vrs_gains g = {VRS_DEVICE_KP, VRS_DEVICE_KI, VRS_DEVICE_KD, VRS_DEVICE_CUTOFF_HZ, VRS_DEVICE_INTEGRAL_LIMIT,
                   VRS_DEVICE_DEADBAND, VRS_DEVICE_HOLD_BAND};
    vrs_gains gains[VRS_DEVICE_N_HINGES];
    int32_t counts[VRS_DEVICE_N_HINGES];
    for (int k = 0; k < VRS_DEVICE_N_HINGES; k++)
        gains[k] = g;
    read_counts(NULL, counts);  /* power on with the flaps flat: these counts are zero */
    vrs_init(&core, &cfg, gains, counts);

    timer = timerBegin(1000000);                       /* 1 MHz timer clock */
    timerAttachInterrupt(timer, &on_timer);
    timerAlarm(timer, 1000000 / VRS_DEVICE_LOOP_RATE_HZ, true, 0);
}

void loop()
{
    if (ticks_done != ticks_due) {  /* the control step runs here, not in the interrupt (float, PCNT calls) */
        ticks_done++;
        vrs_control(&core, &hw);
    }
    vrs_service(&core, &hw);
}
