/* VRScroll firmware core: the protocol, the supervisor and the PID, portable C99.
 *
 * One build runs everywhere: the ESP32-S3 sketch (esp32s3/), the twin and the emulator
 * (through controllers/core.py). All state lives in one fixed-size struct the caller
 * allocates; no heap, no OS calls, float only (the ESP32-S3 FPU is single precision).
 * Data in, data out: vrs_rx / vrs_tx carry the serial bytes, vrs_tick runs one control
 * step on encoder counts and gives duty and decay mode per hinge. vrs_hw is a thin
 * adapter over those calls for hardware (the sketch). See docs/firmware.md.
 */
#ifndef VRS_CORE_H
#define VRS_CORE_H

#include <stddef.h>
#include <stdint.h>

#include "vrs_protocol.h"

#ifdef __cplusplus
extern "C" {
#endif

#define VRS_MAX_HINGES 8
#define VRS_RX_CAP (VRS_MAX_PAYLOAD + VRS_MAX_PAYLOAD / 254 + 2) /* longest COBS frame kept */
#define VRS_TX_CAP 4096u        /* queued bytes for the host */
#define VRS_TX_REPLY_RESERVE 256u /* telemetry is dropped first: it may fill the queue only up to this short of full */
#define VRS_REPLY_MEMORY 4      /* commands whose replies are kept for repeats (same seq) */
#define VRS_REPLY_CAP 16        /* a kept reply's frame: ACK 13 bytes, NACK 11 */
#define VRS_REPLY_KEEP_US 1000000u /* how long: the host's retries come within 0.4 s */
#define VRS_MAX_FIELDS 48       /* values in one message's body, per-hinge arrays spelled out */

/* decay mode per hinge at zero duty (and in the PWM off-time) */
#define VRS_DECAY_COAST 0       /* windings open: the flap turns freely, no back-EMF braking */
#define VRS_DECAY_BRAKE 1       /* windings shorted (slow decay): duty is proportional to voltage */

typedef struct {
    float kp, ki, kd;           /* duty per count, duty per count*s, duty per count/s */
    float cutoff_hz;            /* derivative low-pass cutoff, Hz */
    float integral_limit;       /* duty */
    float deadband;             /* duty */
    uint16_t hold_band;         /* counts */
} vrs_gains;

typedef struct {
    uint8_t n_hinges;
    uint16_t loop_rate_hz;
    uint16_t watchdog_ms;           /* 0 = no watchdog (the twin) */
    uint16_t max_telemetry_hz;
    int32_t limit_counts;           /* targets beyond +-limit_counts are refused */
    int32_t limit_margin_counts;    /* LIMIT fault beyond range + margin */
    float stall_duty;               /* |duty| at or above this ... */
    int32_t stall_counts;           /* ... moving no more than this ... */
    uint16_t stall_ms;              /* ... for longer than this: STALL */
    int16_t overcurrent_ma;         /* 0 = current not sensed */
    uint16_t drive_cap_mv;          /* the motor voltage duty 1 means: vrs_pwm scales by it / battery */
    uint8_t fw_version[3];
    uint16_t stall_current_ma;      /* the motor's current at duty 1 and standstill; 0 = no I2t protection */
    uint16_t continuous_current_ma; /* the motor's continuous rating */
    uint16_t overload_ms;           /* I2t budget: (stall^2 - continuous^2) * this */
    uint16_t host_away_hold_ms;     /* after the watchdog: hold the targets this long (HOLDING), then FAULT */
} vrs_config;

/* the wiring correction: hinge k reads encoder input encoder[k], its motor is on H-bridge bridge[k], and
 * flags[k] (VRS_WIRING_*) turn its encoder's count and its motor's drive around, or disable it (braked, never
 * driven); the identity after vrs_init */
typedef struct {
    uint8_t encoder[VRS_MAX_HINGES];
    uint8_t flags[VRS_MAX_HINGES];
    uint8_t bridge[VRS_MAX_HINGES];
} vrs_wiring;

/* one hinge's PID memory */
typedef struct {
    int32_t prev;               /* counts at the last tick */
    float rate;                 /* filtered counts/s */
    float integral;             /* duty */
} vrs_pid;

/* a reply kept so that a repeated command (same seq, same bytes, within VRS_REPLY_KEEP_US) gets
 * it again instead of running twice; kept for commands that act, forgotten at HELLO */
typedef struct {
    uint8_t used;
    uint16_t seq;
    uint32_t at_us;
    uint16_t request_crc;
    uint16_t len;
    uint8_t payload[VRS_REPLY_CAP];
} vrs_reply;

/* an open-loop duty program on one hinge (PROGRAM, and PULSE as one segment): docs/firmware.md, "Open-loop
 * motion" */
typedef struct {
    uint8_t hinge;              /* the hinge it drives */
    uint8_t n_segments;
    uint16_t timeout_ms;        /* ends it at the latest */
    int32_t low, high;          /* the window, counts */
    float duty[VRS_PROGRAM_MAX_SEGMENTS];
    uint16_t ms[VRS_PROGRAM_MAX_SEGMENTS];
    uint16_t coast;             /* bit i: segment i coasts (windings open, its duty 0; VRS_PROGRAM_COAST on the wire) */
} vrs_program_spec;

/* the last program: how it stands */
typedef struct {
    uint8_t hinge;              /* 0xFF: none since the start */
    uint8_t end;                /* VRS_PROGRAM_END_* (RUNNING while it runs) */
    uint32_t ticks;             /* ticks it ran, one sample each */
    uint32_t dropped;           /* samples the transmit queue had no room for */
    uint16_t battery_mv;        /* read at its end; 0 = not sensed */
} vrs_program_status;

typedef struct {
    vrs_program_spec spec;      /* duties as the wire carries them (duty * VRS_DUTY_SCALE, rounded) */
    vrs_program_status status;
    uint32_t segment_end[VRS_PROGRAM_MAX_SEGMENTS]; /* tick at which each segment ends */
    uint32_t timeout_ticks;
    uint8_t segment;
    uint8_t stream;             /* 1: a PROGRAM_SAMPLE frame per tick (PROGRAM, not PULSE) */
    int32_t history[VRS_PROGRAM_RATE_TICKS]; /* the hinge's counts over the last ticks, for its speed */
    int32_t stall_ref;
    uint32_t stall_since;       /* tick */
    int32_t zero;               /* the hinge's zero and wiring at the start: a change (CONFIRM_ZERO, SET_WIRING) */
    uint8_t encoder, flags, bridge; /* moves the window under the hinge, and ends the program */
} vrs_program_run;

typedef struct vrs_core {
    vrs_config cfg;
    float dt;                                   /* s per tick */
    vrs_gains gains[VRS_MAX_HINGES];
    float alpha[VRS_MAX_HINGES];                /* derivative filter coefficient from cutoff_hz */
    vrs_pid pid[VRS_MAX_HINGES];
    int32_t targets[VRS_MAX_HINGES];
    int32_t counts[VRS_MAX_HINGES];             /* as read at the last tick */
    float duty[VRS_MAX_HINGES];                 /* as written at the last tick */
    int16_t current_ma[VRS_MAX_HINGES];         /* as read at the last tick; 0 if not sensed */
    int32_t stall_ref[VRS_MAX_HINGES];
    uint32_t stall_since_us[VRS_MAX_HINGES];
    int32_t runaway_ref[VRS_MAX_HINGES];        /* counts at the start of a runaway window of one duty sign, */
    uint32_t runaway_since_us[VRS_MAX_HINGES];  /* its start, */
    int32_t runaway_before[VRS_MAX_HINGES];     /* the counts moved against the duty in the window before, */
    uint8_t runaway_windows[VRS_MAX_HINGES];    /* and how many windows in a row moved against it, faster */
    int8_t runaway_sign[VRS_MAX_HINGES];        /* the sign of a duty at or above stall_duty; 0 below */
    int32_t zero[VRS_MAX_HINGES];               /* raw counts at the flat pose (CONFIRM_ZERO) */
    int32_t limit_out[VRS_MAX_HINGES];          /* |counts| beyond this: LIMIT (ratchets in toward the range) */
    float heat[VRS_MAX_HINGES];                 /* I2t estimate above the continuous rating, A^2 s */
    uint8_t derated;                            /* bit k: hinge k held to its continuous rating */
    uint8_t zero_confirmed;
    uint32_t away_since_us;                     /* HOLDING since */
    vrs_wiring wiring;
    uint8_t wiring_changed;                     /* set by SET_WIRING until vrs_take_wiring_change */
    vrs_program_run program;                    /* the open-loop program (PULSE is one) */
    uint8_t state;
    uint16_t faults;
    uint8_t fault_hinge;
    uint32_t now_us;                            /* device time of the last call */
    uint32_t last_rx_us;                        /* last valid frame from the host */
    uint32_t ticks;
    uint16_t telemetry_every;                   /* ticks between telemetry frames; 0 = off */
    uint16_t telemetry_seq;
    uint32_t telemetry_dropped;
    uint32_t rx_bad_frames;
    uint32_t rx_good_frames;
    uint16_t battery_mv;                        /* last battery reading (vrs_set_battery_mv); 0 = not sensed */
    uint8_t battery_implausible;                /* vrs_set_battery_plausible(c, 0): FAULT BATTERY persists */
    uint8_t reset_reason;                       /* why the device last started (esp_reset_reason_t), for HELLO */
    uint8_t setup_error;                        /* VRS_SETUP_*: the first set-up call that failed; 0 none */
    uint8_t rx_buf[VRS_RX_CAP];
    uint16_t rx_len;
    uint8_t rx_overflow;
    uint8_t tx_buf[VRS_TX_CAP];
    uint32_t tx_head, tx_len;                   /* ring buffer */
    vrs_reply replies[VRS_REPLY_MEMORY];
    uint8_t reply_next;
} vrs_core;

size_t vrs_core_size(void);

/* Start: config, gains for n_hinges hinges, present counts (targets start there). 0, or -1 for a
 * config the core cannot run (no hinges, more than VRS_MAX_HINGES, no loop rate, gains out of bounds). */
int vrs_init(vrs_core *c, const vrs_config *cfg, const vrs_gains *gains, const int32_t *counts_now);

/* Bytes from the host: parse, execute, queue replies. now_us: device time. */
void vrs_rx(vrs_core *c, const uint8_t *bytes, uint32_t n, uint32_t now_us);

/* Take up to max queued bytes for the host; returns how many. */
uint32_t vrs_tx(vrs_core *c, uint8_t *out, uint32_t max);

/* One control tick: supervisor, PID, I2t, telemetry. counts: raw encoder inputs (the wiring correction and
 * the zero are applied here); current_ma per H-bridge, NULL when not sensed. Writes duty_out[b] in [-1, 1]
 * and decay_out[b] (VRS_DECAY_*) for each H-bridge b (the hinge whose motor is on it, its motor flag
 * applied). */
void vrs_tick(vrs_core *c, uint32_t now_us, const int32_t *counts, const int16_t *current_ma,
              float *duty_out, uint8_t *decay_out);

/* The battery voltage now, mV (the device's ADC through the divider; the twin's and the emulator's pack). */
void vrs_set_battery_mv(vrs_core *c, uint16_t mv);
/* Whether the battery reading is plausible (the board's bounds); not: FAULT BATTERY, which CLEAR_FAULT
 * cannot clear while it stays so. */
void vrs_set_battery_plausible(vrs_core *c, int plausible);

/* Battery compensation: the H-bridges' PWM (per bridge, as duty_out) for the last tick's duties, in [-1, 1]. Duty 1 means
 * drive_cap_mv at the motor, so pwm = duty * drive_cap_mv / battery_mv, clamped (a pack sagging below the
 * cap gives what it has); with no battery reading (0) pwm = duty. */
void vrs_pwm(const vrs_core *c, float *pwm_out);

/* 0, or the NACK reason (VRS_NACK_*); nothing changes on a refusal. SET_TARGETS calls these. */
int vrs_set_targets(vrs_core *c, const int32_t *counts, uint32_t now_us);
int vrs_set_gains(vrs_core *c, uint8_t hinge /* VRS_BROADCAST: all */, const vrs_gains *g);
int vrs_set_telemetry_rate(vrs_core *c, uint16_t rate_hz);
void vrs_estop(vrs_core *c);
int vrs_clear_fault(vrs_core *c);  /* 0, or VRS_NACK_FAULT_PERSISTS while a HARDWARE fault stands */

/* Start an open-loop program (PROGRAM does this): 0, or the NACK reason (VRS_NACK_*); nothing changes on a
 * refusal. IDLE, zero confirmed, no program running; hinge < n; 1..VRS_PROGRAM_MAX_SEGMENTS segments of 1 ms or
 * more, VRS_PROGRAM_MAX_MS in all; |duty| <= VRS_PROGRAM_MAX_DUTY (compared in wire units: duty is rounded to
 * duty * VRS_DUTY_SCALE first); a coasting segment's (p->coast) duty 0, no coast bit past the last segment;
 * timeout 1..VRS_PROGRAM_MAX_MS; -limit_counts <= low < high <= limit_counts with the hinge's counts inside. Its
 * samples stream as PROGRAM_SAMPLE frames. */
int vrs_program(vrs_core *c, const vrs_program_spec *p);
void vrs_get_program(const vrs_core *c, vrs_program_status *out);

/* The flaps lie flat now: the present counts become zero (CONFIRM_ZERO does this); 0, or VRS_NACK_BAD_STATE
 * outside IDLE. vrs_mark_zero_confirmed accepts the present zero as it is (the twin, whose counts are true). */
int vrs_confirm_zero(vrs_core *c);
void vrs_mark_zero_confirmed(vrs_core *c);
/* The I2t estimate per hinge as a share of the budget (1: derating), and the derated hinges' bits. */
void vrs_get_heat(const vrs_core *c, float *share_out);
uint8_t vrs_get_derated(const vrs_core *c);

/* The wiring correction (SET_WIRING calls vrs_set_wiring): 0, or VRS_NACK_BAD_STATE outside IDLE,
 * VRS_NACK_BAD_VALUE for encoders or bridges that are not a permutation, or unknown flags. A change leaves the zero
 * unconfirmed. The board stores it where it survives a power cycle: vrs_take_wiring_change gives it (1) once
 * after each change; at boot the board gives it back with vrs_set_wiring. */
int vrs_set_wiring(vrs_core *c, const vrs_wiring *w);
void vrs_get_wiring(const vrs_core *c, vrs_wiring *out);
int vrs_take_wiring_change(vrs_core *c, vrs_wiring *out);
/* Bit k: hinge k is disabled (flags[k] & VRS_WIRING_DISABLED): braked in every state, its PULSE and PROGRAM
 * refused and a target that moves it (more than stall_counts from where it stands) refused, VRS_NACK_HINGE_DISABLED
 * naming it; CLEAR_FAULT and a restart keep it (it is the wiring's). Disabling or enabling a hinge alone keeps the
 * zero. */
uint8_t vrs_get_disabled(const vrs_core *c);

/* The board's start, after vrs_init: why it reset (esp_reset_reason_t, reported in HELLO_REPLY), and a
 * set-up call that failed (VRS_SETUP_*, for the hinge it was setting up, 0xFF for the board): the core
 * goes to FAULT with VRS_FAULT_HARDWARE, which CLEAR_FAULT cannot clear; only the first failure is kept. */
void vrs_set_reset_reason(vrs_core *c, uint8_t reason);
void vrs_hardware_fault(vrs_core *c, uint8_t step, uint8_t hinge);

/* read-only accessors */
uint8_t vrs_get_state(const vrs_core *c);
uint16_t vrs_get_faults(const vrs_core *c);
uint8_t vrs_get_fault_hinge(const vrs_core *c);
void vrs_get_targets(const vrs_core *c, int32_t *out);
int vrs_get_gains(const vrs_core *c, uint8_t hinge, vrs_gains *out);  /* 0, or VRS_NACK_BAD_VALUE */
uint32_t vrs_get_rx_bad_frames(const vrs_core *c);
uint32_t vrs_get_telemetry_dropped(const vrs_core *c);
uint16_t vrs_get_battery_mv(const vrs_core *c);
vrs_pid *vrs_pid_memory(vrs_core *c);  /* the PID memory, one per hinge: the twin carries it across a reset */

/* The PID of controllers/pid.py for one hinge and tick, in float: updates s, returns duty. */
float vrs_pid_update(vrs_pid *s, const vrs_gains *g, float alpha, float dt, int32_t target, int32_t counts);
/* The derivative filter's coefficient dt / (dt + 1 / (2 pi cutoff_hz)). */
float vrs_pid_alpha(float cutoff_hz, float dt);

/* Wire codec (vrs_wire.c), the one the core speaks; also used by the tests' golden frames.
 * values: the body's fields in the order of vrs_protocol.h's VRS_MESSAGES table (fixed fields,
 * then each per-hinge field as an array of n), as 32-bit patterns (signed fields sign-extended). */
uint16_t vrs_crc16(const uint8_t *data, uint32_t n);
uint32_t vrs_cobs_encode(const uint8_t *in, uint32_t n, uint8_t *out);        /* out: n + n/254 + 1 */
int32_t vrs_cobs_decode(const uint8_t *in, uint32_t n, uint8_t *out);         /* -1: malformed */
uint32_t vrs_encode(uint8_t msg_id, uint16_t seq, const uint32_t *values, uint8_t n, uint8_t *out, uint32_t max);
/* Decode one frame without its 0x00: <0 dropped (VRS_DROP_*), 0 fine, >0 the NACK reason. */
int vrs_decode(const uint8_t *frame, uint32_t len, uint8_t *msg_id, uint16_t *seq, uint32_t *values, uint8_t *n);

#define VRS_DROP_COBS (-1)
#define VRS_DROP_SHORT (-2)
#define VRS_DROP_CRC (-3)

/* hardware access: what the device (and only it) implements */
typedef struct {
    void *ctx;
    uint32_t (*micros)(void *ctx);
    void (*read_counts)(void *ctx, int32_t *counts);
    void (*write_drive)(void *ctx, const float *duty, const uint8_t *decay);
    int (*serial_read)(void *ctx, uint8_t *buf, int max);
    void (*serial_write)(void *ctx, const uint8_t *buf, int n);  /* never blocks: n <= serial_room() */
    int (*serial_room)(void *ctx);                      /* bytes serial_write takes now without waiting */
    int (*read_current_ma)(void *ctx, int16_t *ma);    /* optional (NULL); 0 on success */
    int (*read_battery_mv)(void *ctx, uint16_t *mv);   /* optional (NULL); 0 on success */
} vrs_hw;

void vrs_service(vrs_core *c, const vrs_hw *hw);   /* serial in -> vrs_rx, vrs_tx -> serial out, as much as there is room for */
void vrs_control(vrs_core *c, const vrs_hw *hw);   /* one tick through hw: read, vrs_tick, write */

#ifdef __cplusplus
}
#endif

#endif
