/* VRScroll on an ESP32-S3-DevKitC-1: every pin in one place (docs/firmware.md, "Wiring").
 * Hinge k is the hinge between flap k and flap k + 1, counted from the end with the lowest x.
 * Avoided: strapping pins 0, 3, 45, 46; USB 19, 20; flash and PSRAM 26-37.
 * The host build (host/, controllers/sketch.py) reads these arrays as the board's wiring. */
#ifndef VRS_PINS_H
#define VRS_PINS_H

/* quadrature encoder channels A and B, per hinge (3.3 V logic; the motor's Hall encoder runs on 3.3 V).
 * Sign convention, both decoders: A leading B (A rises while B is low) counts up. */
static const int PIN_ENC_A[6] = {4, 6, 8, 10, 12, 14};
static const int PIN_ENC_B[6] = {5, 7, 9, 11, 13, 15};

/* DRV8833 inputs per hinge: IN1 and IN2 of one H-bridge (three DRV8833 boards, two bridges each).
 * IN1 high with IN2 low drives forward (counts up); both high brake; both low coast. */
static const int PIN_IN1[6] = {16, 18, 38, 40, 42, 48};
static const int PIN_IN2[6] = {17, 21, 39, 41, 47, 2};

/* The DevKitC-1's RGB LED (a WS2812) takes its data from GPIO48 on board v1.0 and from GPIO38 on v1.1: hinge
 * 5's IN1 or hinge 2's IN1 here, the S3 having no free output left. The sketch never writes the LED; its
 * data input (high impedance) reads the bridge's PWM as colour data, so it flickers while that hinge drives,
 * and nothing else. (Arduino's own PIN_RGB_LED, variants/esp32s3, says 48 whatever the revision.) */
#define PIN_DEVKIT_V1_0_RGB_LED 48
#define PIN_DEVKIT_V1_1_RGB_LED 38

/* battery through a divider (ADC1 channel 0; ADC2 is unusable while Wi-Fi runs) */
#define PIN_BATTERY 1
#define BATTERY_DIVIDER 3  /* 20 kOhm over 10 kOhm: 8.4 V (2S full) -> 2.8 V at the pin */
/* what a 2S pack can read through it, mV: above a flat pack sagging under six stalled motors (2 x 2.25 V),
 * below a full one with the ADC's error (8.4 V + 0.6 V); outside, the divider or the ADC is broken (an open
 * lower resistor reads the ADC's top, 9.3 V; an open upper one, or no pack, 0) */
#define BATTERY_MIN_MV 4500
#define BATTERY_MAX_MV 9000
#define BATTERY_FILTER_TICKS 16  /* the plausibility check's first-order low-pass, ticks (16 ms at 1 kHz) */

/* the ESP32-S3 has four PCNT units: hinges 0-3 count in hardware, 4-5 in a pin-change interrupt, which
 * reads A and B in one read of GPIO_IN_REG: their pins must be below 32 */
#define N_PCNT_HINGES 4

/* PWM: MCPWM, whose two groups of three operators with two generators each drive six H-bridges with no
 * pin ever re-routed (LEDC has 8 channels on the S3, too few for 12 inputs). Timer clock 10 MHz (the
 * group's 160 MHz PLL clock / 2 / 8), 500 ticks a period: 20 kHz, above hearing, 500 duty steps. */
#ifndef PWM_RESOLUTION_HZ /* overridable for the host build's tests (controllers.sketch.build(defines)) */
#define PWM_RESOLUTION_HZ 10000000
#endif
#ifndef PWM_PERIOD_TICKS
#define PWM_PERIOD_TICKS 500
#endif
#define PWM_HINGES_PER_GROUP 3

#endif
