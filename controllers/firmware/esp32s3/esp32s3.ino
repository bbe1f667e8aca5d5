/* VRScroll firmware for the ESP32-S3 (Arduino core 3.x on ESP-IDF 5.x): the hardware-access struct of the
 * portable core (controllers/firmware/vrs_core.h) and nothing else. Every decision (protocol, states,
 * watchdog, faults, PID) is the core's; this file reads encoders and the battery, drives six DRV8833
 * H-bridges through MCPWM, keeps the 1 kHz tick and moves serial bytes without ever waiting on the host.
 * Every set-up call is checked: the first that fails is reported to the host as a HARDWARE fault naming
 * it (VRS_SETUP_*). The host build (controllers/sketch.py) compiles this file unchanged against stand-ins
 * for the calls it makes. docs/firmware.md has the wiring, the build commands and the bring-up. */
#include <Arduino.h>
#include <Preferences.h>
#include <driver/gpio.h>
#include <driver/mcpwm_prelude.h>
#include <driver/pulse_cnt.h>
#include <esp_system.h>
#include <soc/gpio_reg.h>
#include <soc/soc.h>

#include "pins.h"
#include "vrs_core.h"

vrs_core core;  /* not static: the host build (controllers/sketch.py) reads its state */
static pcnt_unit_handle_t pcnt[N_PCNT_HINGES];
static volatile int32_t soft_counts[6];        /* hinges N_PCNT_HINGES.. : decoded in the interrupt */
static volatile uint8_t soft_state[6];
volatile uint32_t soft_illegal[6];  /* both channels changed between two interrupts: an edge lost (not static:
                                       the host build reads it) */
static volatile uint32_t ticks_due;             /* written by the timer interrupt only */
static volatile uint32_t ticks_done;            /* written by loop() only */
static hw_timer_t *timer;
static mcpwm_cmpr_handle_t compare_in1[6], compare_in2[6];
static mcpwm_gen_handle_t gen_in1[6], gen_in2[6];
static int8_t drive_dir[6];                    /* +1 forward, -1 reverse, 0 stopped: which generator is forced */
static uint8_t stop_decay[6];                   /* decay while stopped (VRS_DECAY_*) */
static uint8_t setup_step, setup_hinge = 0xFF; /* the first set-up call that failed */
static Preferences prefs;                      /* NVS: the wiring correction bring-up stored */

/* remember the first failed set-up call; true if this one failed */
static bool failed(esp_err_t err, uint8_t step, int hinge)
{
    if (err == ESP_OK)
        return false;
    if (!setup_step) {
        setup_step = step;
        setup_hinge = (uint8_t)hinge;
    }
    return true;
}

/* ---- encoders: one sign convention, A leading B counts up (pins.h) ------------------------------ */

static void pcnt_setup(int k)
{
    pcnt_unit_config_t unit = {};
    unit.low_limit = -32768;
    unit.high_limit = 32767;
    unit.flags.accum_count = 1;  /* the driver extends the 16-bit counter at the watch points on the limits */
    if (failed(pcnt_new_unit(&unit, &pcnt[k]), VRS_SETUP_ENCODER_COUNTER, k))
        return;
    pcnt_glitch_filter_config_t filter = {.max_glitch_ns = 1000};
    pcnt_chan_config_t a = {}, b = {};
    a.edge_gpio_num = PIN_ENC_A[k];
    a.level_gpio_num = PIN_ENC_B[k];
    b.edge_gpio_num = PIN_ENC_B[k];
    b.level_gpio_num = PIN_ENC_A[k];
    pcnt_channel_handle_t ca = NULL, cb = NULL;
    /* x4 quadrature: A's edges count up when rising with B low, B's when rising with A high */
    if (failed(pcnt_unit_set_glitch_filter(pcnt[k], &filter), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_new_channel(pcnt[k], &a, &ca), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_new_channel(pcnt[k], &b, &cb), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_channel_set_edge_action(ca, PCNT_CHANNEL_EDGE_ACTION_INCREASE, PCNT_CHANNEL_EDGE_ACTION_DECREASE),
                  VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_channel_set_level_action(ca, PCNT_CHANNEL_LEVEL_ACTION_INVERSE, PCNT_CHANNEL_LEVEL_ACTION_KEEP),
                  VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_channel_set_edge_action(cb, PCNT_CHANNEL_EDGE_ACTION_INCREASE, PCNT_CHANNEL_EDGE_ACTION_DECREASE),
                  VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_channel_set_level_action(cb, PCNT_CHANNEL_LEVEL_ACTION_KEEP, PCNT_CHANNEL_LEVEL_ACTION_INVERSE),
                  VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_unit_add_watch_point(pcnt[k], unit.low_limit), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_unit_add_watch_point(pcnt[k], unit.high_limit), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_unit_enable(pcnt[k]), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_unit_clear_count(pcnt[k]), VRS_SETUP_ENCODER_COUNTER, k)
        || failed(pcnt_unit_start(pcnt[k]), VRS_SETUP_ENCODER_COUNTER, k))
        return;
}

/* Gray-code step for (previous AB, new AB) with AB = A << 1 | B: +1 for 00 -> 10 -> 11 -> 01 -> 00 */
static const int8_t QUAD_STEP[16] = {0, -1, 1, 0, 1, 0, 0, -1, -1, 0, 0, 1, 0, 1, -1, 0};

/* A and B from one read of GPIO_IN_REG (GPIO0-31 at one instant; pins.h keeps these hinges' pins below 32):
 * two digitalReads apart could see A before and B after another edge, a state that never was. A change of
 * both at once cannot be counted (which way?): it is counted as illegal instead. */
static void IRAM_ATTR soft_encoder(void *arg)
{
    int k = (int)(intptr_t)arg;
    uint32_t in = REG_READ(GPIO_IN_REG);
    uint8_t ab = (uint8_t)(((in >> PIN_ENC_A[k]) & 1u) << 1 | ((in >> PIN_ENC_B[k]) & 1u));
    if ((soft_state[k] ^ ab) == 3u)
        soft_illegal[k]++;
    soft_counts[k] += QUAD_STEP[soft_state[k] << 2 | ab];
    soft_state[k] = ab;
}

static void read_counts(void *ctx, int32_t *counts)
{
    (void)ctx;
    for (int k = 0; k < 6; k++) {
        if (k < N_PCNT_HINGES) {
            int c = 0;
            if (pcnt[k])
                pcnt_unit_get_count(pcnt[k], &c);
            counts[k] = c;
        } else {
            counts[k] = soft_counts[k];
        }
    }
}

/* ---- motors: MCPWM, set up once, only compare values and forced levels change in the tick ---------- */

/* Every generator's output is inverted in the GPIO matrix (invert_pwm): a generator just made, reset and
 * low, holds its pin high, so the hand-over from the GPIO (set high in setup()) to MCPWM never lets an
 * input fall (ESP-IDF v5.4 mcpwm_gen.c, mcpwm_new_generator: the generator reset, then the signal
 * connected with its invert flag). The pin's level (1 high, 0 low, -1 to the PWM actions) as the force: */
static esp_err_t force_pin(mcpwm_gen_handle_t gen, int level)
{
    return mcpwm_generator_set_force_level(gen, level < 0 ? -1 : 1 - level, true);
}

/* One H-bridge on operator `op`: each input goes low at the period's start and high at its comparator
 * (the generator high, then low: inverted), so an input is low for `compare` ticks of the period. */
static void bridge_setup(int k, mcpwm_timer_handle_t tmr, int group)
{
    mcpwm_oper_handle_t op = NULL;
    mcpwm_operator_config_t oc = {};
    oc.group_id = group;
    mcpwm_comparator_config_t cc = {};
    cc.flags.update_cmp_on_tez = 1;
    if (failed(mcpwm_new_operator(&oc, &op), VRS_SETUP_PWM_OPERATOR, k)
        || failed(mcpwm_operator_connect_timer(op, tmr), VRS_SETUP_PWM_OPERATOR, k)
        || failed(mcpwm_new_comparator(op, &cc, &compare_in1[k]), VRS_SETUP_PWM_COMPARATOR, k)
        || failed(mcpwm_new_comparator(op, &cc, &compare_in2[k]), VRS_SETUP_PWM_COMPARATOR, k))
        return;
    mcpwm_gen_handle_t *gens[2] = {&gen_in1[k], &gen_in2[k]};
    mcpwm_cmpr_handle_t cmps[2] = {compare_in1[k], compare_in2[k]};
    const int pins[2] = {PIN_IN1[k], PIN_IN2[k]};
    for (int i = 0; i < 2; i++) {
        mcpwm_generator_config_t gc = {};
        gc.gen_gpio_num = pins[i];
        gc.flags.invert_pwm = 1;
        if (failed(mcpwm_new_generator(op, &gc, gens[i]), VRS_SETUP_PWM_GENERATOR, k)
            || failed(force_pin(*gens[i], 1), VRS_SETUP_PWM_GENERATOR, k)  /* brake */
            || failed(mcpwm_generator_set_action_on_timer_event(*gens[i],
                          MCPWM_GEN_TIMER_EVENT_ACTION(MCPWM_TIMER_DIRECTION_UP, MCPWM_TIMER_EVENT_EMPTY,
                                                       MCPWM_GEN_ACTION_HIGH)), VRS_SETUP_PWM_GENERATOR, k)
            || failed(mcpwm_generator_set_action_on_compare_event(*gens[i],
                          MCPWM_GEN_COMPARE_EVENT_ACTION(MCPWM_TIMER_DIRECTION_UP, cmps[i], MCPWM_GEN_ACTION_LOW)),
                      VRS_SETUP_PWM_GENERATOR, k))
            return;
    }
    drive_dir[k] = 0;
    stop_decay[k] = VRS_DECAY_BRAKE;
}

/* DRV8833: IN1 IN2 = 1 0 forward, 0 1 reverse, 1 1 brake, 0 0 coast. Driving uses slow decay: one input
 * forced high, the other low for the duty's share of each period and high (brake) for the rest. */
static void write_drive(void *ctx, const float *pwm, const uint8_t *decay)
{
    (void)ctx;
    for (int k = 0; k < 6; k++) {
        if (!gen_in1[k] || !gen_in2[k])
            continue;
        float mag = pwm[k] < 0.0f ? -pwm[k] : pwm[k];
        uint32_t on = (uint32_t)(mag * (float)PWM_PERIOD_TICKS + 0.5f);
        int8_t dir = on == 0 ? 0 : (pwm[k] > 0.0f ? 1 : -1);
        if (dir != drive_dir[k] || (dir == 0 && decay[k] != stop_decay[k])) {
            int level1 = dir > 0 ? 1 : (dir < 0 ? -1 : (decay[k] == VRS_DECAY_BRAKE ? 1 : 0));
            int level2 = dir < 0 ? 1 : (dir > 0 ? -1 : (decay[k] == VRS_DECAY_BRAKE ? 1 : 0));
            force_pin(gen_in1[k], level1);
            force_pin(gen_in2[k], level2);
            drive_dir[k] = dir;
            stop_decay[k] = decay[k];
        }
        if (dir != 0)
            mcpwm_comparator_set_compare_value(dir > 0 ? compare_in2[k] : compare_in1[k], on);
    }
}

/* ---- clock, serial, battery --------------------------------------------------------------------- */

static uint32_t micros_now(void *ctx) { (void)ctx; return (uint32_t)micros(); }

static int serial_read(void *ctx, uint8_t *buf, int max)
{
    (void)ctx;
    int n = Serial.available();
    return n > 0 ? (int)Serial.read(buf, (size_t)(n < max ? n : max)) : 0;
}

static int serial_room(void *ctx) { (void)ctx; return Serial.availableForWrite(); }

static void serial_write(void *ctx, const uint8_t *buf, int n) { (void)ctx; Serial.write(buf, (size_t)n); }

/* The pack through the divider. Its plausibility is judged on the reading low-passed over
 * BATTERY_FILTER_TICKS (one noisy or dropped sample moves it by a sixteenth): outside BATTERY_MIN_MV..
 * BATTERY_MAX_MV the core faults BATTERY and compensates as for the spec's nominal pack
 * (VRS_DEVICE_SUPPLY_MV). Within them it compensates for this tick's reading where that is plausible too (a
 * pack sagging under load is followed at once), else for the filtered one: never for an implausible value
 * (a divider reading 150 mV would multiply the loop's gain by 40, a reading of 0 remove compensation). */
static uint32_t battery_sum;  /* BATTERY_FILTER_TICKS x the filtered mV; 0 before the first reading */
static bool battery_plausible(uint32_t mv) { return mv >= BATTERY_MIN_MV && mv <= BATTERY_MAX_MV; }
static int read_battery_mv(void *ctx, uint16_t *mv)
{
    (void)ctx;
    uint32_t raw = analogReadMilliVolts(PIN_BATTERY) * BATTERY_DIVIDER;
    battery_sum = battery_sum ? battery_sum - battery_sum / BATTERY_FILTER_TICKS + raw : raw * BATTERY_FILTER_TICKS;
    uint32_t filtered = battery_sum / BATTERY_FILTER_TICKS;
    vrs_set_battery_plausible(&core, battery_plausible(filtered));
    *mv = (uint16_t)(!battery_plausible(filtered) ? VRS_DEVICE_SUPPLY_MV : battery_plausible(raw) ? raw : filtered);
    return 0;
}

static const vrs_hw hw = {NULL, micros_now, read_counts, write_drive, serial_read, serial_write, serial_room,
                          NULL /* the DRV8833 reports no current */, read_battery_mv};

/* The brake that does not need loop(): should loop() fall more than LOOP_LATE_TICKS ticks behind the
 * timer (a wait that never ends, a bug), the timer's interrupt sets every compare value to 0, so every
 * bridge brakes from the next PWM period: the driven input high for the whole period beside the one
 * forced high (at compare 0 a generator high at EMPTY and low at the compare stays low: ESP-IDF v5.4.1's
 * test app, test_mcpwm_gen.c "mcpwm_duty_empty_full"). mcpwm_comparator_set_compare_value is the MCPWM call ESP-IDF allows in an
 * ISR (docs: "MCPWM", ISR and thread safety). loop(), once back, writes its own compare values again.
 * The task watchdog (enableLoopWDT, 5 s) then resets a board whose loop() does not come back. */
#ifndef LOOP_LATE_TICKS /* overridable for the host build's benchmark (the brake taken out) */
#define LOOP_LATE_TICKS 3
#endif
static void IRAM_ATTR on_timer()
{
    ticks_due++;
    if (ticks_due - ticks_done > LOOP_LATE_TICKS)
        for (int k = 0; k < 6; k++)
            if (compare_in1[k] && compare_in2[k]) {
                mcpwm_comparator_set_compare_value(compare_in1[k], 0);
                mcpwm_comparator_set_compare_value(compare_in2[k], 0);
            }
}

void setup()
{
    /* brake first: the board's pull-ups held every input high through reset and boot (docs/firmware.md,
     * "Wiring"); the output register is set high before the output is enabled, so the first level the pin
     * drives is high. Arduino-ESP32 3.x refuses digitalWrite on a pin pinMode has not made GPIO, and its
     * pinMode leaves the register as it was (low after reset): digitalWrite first would coast, so
     * ESP-IDF's gpio_set_level, which writes the register in any mode, comes first. Should MCPWM then fail
     * to start, these pins stay GPIO outputs, high: braked. */
    for (int k = 0; k < 6; k++) {
        gpio_set_level((gpio_num_t)PIN_IN1[k], 1);
        gpio_set_level((gpio_num_t)PIN_IN2[k], 1);
        pinMode(PIN_IN1[k], OUTPUT);
        pinMode(PIN_IN2[k], OUTPUT);
    }
    failed(Serial.setRxBufferSize(1024) ? ESP_OK : ESP_FAIL, VRS_SETUP_SERIAL, 0xFF);
    Serial.setTxTimeoutMs(0);  /* never wait on a host that does not read; serial_room keeps writes whole */
    Serial.begin(921600);      /* USB CDC: the rate is ignored */

    mcpwm_timer_handle_t timers[2] = {NULL, NULL};
    for (int g = 0; g < 2; g++) {
        mcpwm_timer_config_t tc = {};
        tc.group_id = g;
        tc.clk_src = MCPWM_TIMER_CLK_SRC_DEFAULT;
        tc.resolution_hz = PWM_RESOLUTION_HZ;
        tc.count_mode = MCPWM_TIMER_COUNT_MODE_UP;
        tc.period_ticks = PWM_PERIOD_TICKS;
        if (failed(mcpwm_new_timer(&tc, &timers[g]), VRS_SETUP_PWM_TIMER, 0xFF))
            continue;
        for (int k = g * PWM_HINGES_PER_GROUP; k < (g + 1) * PWM_HINGES_PER_GROUP; k++)
            bridge_setup(k, timers[g], g);
        if (!failed(mcpwm_timer_enable(timers[g]), VRS_SETUP_PWM_TIMER, 0xFF))
            failed(mcpwm_timer_start_stop(timers[g], MCPWM_TIMER_START_NO_STOP), VRS_SETUP_PWM_TIMER, 0xFF);
    }

    for (int k = 0; k < 6; k++) {
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

    vrs_config cfg = VRS_DEVICE_CONFIG;
    vrs_gains g = VRS_DEVICE_GAINS;
    vrs_gains gains[VRS_DEVICE_N_HINGES];
    int32_t counts[VRS_DEVICE_N_HINGES];
    for (int k = 0; k < VRS_DEVICE_N_HINGES; k++)
        gains[k] = g;
    read_counts(NULL, counts);  /* zero unconfirmed: SET_TARGETS is refused until the host's CONFIRM_ZERO */
    vrs_init(&core, &cfg, gains, counts);
    vrs_set_reset_reason(&core, (uint8_t)esp_reset_reason());
    vrs_wiring wiring;  /* the correction `vrscroll bringup` stored, its disabled hinges too: from the first tick */
    if (prefs.begin("vrscroll", false) && prefs.getBytesLength("wiring") == sizeof wiring
        && prefs.getBytes("wiring", &wiring, sizeof wiring) == sizeof wiring)
        vrs_set_wiring(&core, &wiring);
    vrs_take_wiring_change(&core, &wiring);  /* loaded, not changed */

    timer = timerBegin(1000000);  /* 1 MHz timer clock */
    if (timer == NULL) {
        failed(ESP_FAIL, VRS_SETUP_TICK_TIMER, 0xFF);
    } else {
        timerAttachInterrupt(timer, &on_timer);
        timerAlarm(timer, 1000000 / VRS_DEVICE_LOOP_RATE_HZ, true, 0);
    }
    if (setup_step)
        vrs_hardware_fault(&core, setup_step, setup_hinge);
    enableLoopWDT();  /* the task watchdog resets the board should loop() ever hold */
}

void loop()
{
    if (ticks_done != ticks_due) {  /* the control step runs here, not in the interrupt (float, PCNT calls) */
        ticks_done++;
        vrs_control(&core, &hw);
    }
    vrs_service(&core, &hw);
    vrs_wiring wiring;
    if (vrs_take_wiring_change(&core, &wiring))  /* SET_WIRING: kept across power cycles */
        prefs.putBytes("wiring", &wiring, sizeof wiring);
}
