/* Host stand-ins for the ESP32-S3 peripherals the sketch uses, and the plant's side of the board.
 *
 * Each stand-in keeps the behaviour and the limits that Espressif documents, and refuses what the
 * driver refuses with the same error (sources named per section). Time is virtual: the host advances
 * it (host_advance), the timer alarm fires the sketch's interrupt, loop() runs after it. The plant
 * (controllers/sketch.py) sets each motor's encoder position (host_set_encoder: every quadrature edge
 * between the old count and the new one, so PCNT units and pin interrupts see real edges), the
 * battery's voltage at the ADC pin, and reads each H-bridge's drive over the last window
 * (host_bridge: the DRV8833 truth table over the PWM period, averaged over time).
 * Units: us, mV, counts. Not modelled: silicon timing (every call takes no time), electrical noise
 * (edges are clean, so the glitch filter only has its bounds checked), the USB link's own timing. */
#include <string.h>

#include "Arduino.h"
#include "Preferences.h"
#include "driver/gpio.h"
#include "driver/mcpwm_prelude.h"
#include "driver/pulse_cnt.h"
#include "esp_system.h"
#include "soc/gpio_reg.h"
#include "soc/soc.h"

extern void setup(void);
extern void loop(void);

#define N_GPIO 49          /* GPIO0-48 on the ESP32-S3 */
#define N_MOTORS 8
#define APB_HZ 80000000u   /* APB clock, Hz (ESP32-S3 TRM, "Clock") */

static uint64_t now_us;
static esp_reset_reason_t reset_reason = ESP_RST_POWERON;
static void integrate(void);

/* Set-up takes time on the board: each GPIO call and each driver call (an allocation, a lock, a log line)
 * moves the clock on, so what the pins hold between two set-up calls is integrated into the bridges'
 * states. Assumed costs, of the S3's order at 240 MHz (not measured on silicon). ROM_BOOT_US: from a reset
 * to setup(), the ROM, the second-stage bootloader and Arduino's start-up, in which no pin is the sketch's
 * (assumed; the S3's boot log shows a few hundred ms, most of it loading the app from flash). */
#define GPIO_CALL_US 2u
#define DRIVER_CALL_US 20u
#define ROM_BOOT_US 300000u
static void spend(uint32_t us)
{
    integrate();
    now_us += us;
}

unsigned long micros(void) { return (unsigned long)(uint32_t)now_us; }  /* 32 bits, wrapping, as on the S3 */

/* ---- GPIO (esp32-hal-gpio.c): levels, outputs, interrupts ---------------------------------------- */

struct host_mcpwm_gen;
struct pin_state {
    uint8_t mode;            /* 0 unconfigured (input, high impedance) */
    uint8_t gpio;            /* set as GPIO by pinMode (Arduino 3.x's peripheral manager: ESP32_BUS_TYPE_GPIO) */
    uint8_t pull_up;         /* the board's own pull-up on the pin (host_pull_up) */
    uint8_t out;             /* the output register (gpio_set_level, digitalWrite on a GPIO pin) */
    uint8_t in;              /* level the outside world drives (encoder pins) */
    struct host_mcpwm_gen *gen;  /* routed to an MCPWM generator */
    void (*isr)(void *);
    void *isr_arg;
    int isr_mode;
};
static pin_state pins[N_GPIO];

static void pcnt_edge(int pin, int level);

/* Arduino-ESP32 3.x (cores/esp32/esp32-hal-gpio.c): pinMode detaches the pin from any peripheral (the
 * peripheral manager), configures it with gpio_config, which leaves the output register as it was, and
 * marks it as GPIO; digitalWrite on a pin not so marked is refused ("IO %u is not set as GPIO. Execute
 * digitalMode(%u, OUTPUT) first.") and changes nothing. ESP-IDF's gpio_set_level writes the output
 * register whatever the pin's mode, so a level set before pinMode(OUTPUT) is the level it drives. */
void pinMode(uint8_t pin, uint8_t mode)
{
    if (pin >= N_GPIO)
        return;
    spend(GPIO_CALL_US);
    pins[pin].mode = mode;
    pins[pin].gpio = 1;
    pins[pin].gen = NULL;
}

void digitalWrite(uint8_t pin, uint8_t val)
{
    if (pin >= N_GPIO)
        return;
    spend(GPIO_CALL_US);
    if (pins[pin].gpio && !pins[pin].gen)
        pins[pin].out = val ? 1 : 0;
}

esp_err_t gpio_set_level(gpio_num_t gpio_num, uint32_t level)
{
    if (gpio_num < 0 || gpio_num >= N_GPIO)
        return ESP_ERR_INVALID_ARG;
    spend(GPIO_CALL_US);
    pins[gpio_num].out = level ? 1 : 0;
    return ESP_OK;
}

/* An input read takes time: an encoder edge due (host_set_encoder_racing) lands just after it, and its
 * interrupt runs once the one reading has returned, as a second edge inside an interrupt's latency does. */
static int race_pin = -1, race_level, isr_pending = -1;
static int pin_level(int pin) { return pins[pin].mode == OUTPUT ? pins[pin].out : pins[pin].in; }
static void race_lands(void)
{
    if (race_pin < 0)
        return;
    int p = race_pin;
    race_pin = -1;
    pins[p].in = (uint8_t)race_level;
    pcnt_edge(p, race_level);
    isr_pending = p;
}

int digitalRead(uint8_t pin)
{
    if (pin >= N_GPIO)
        return 0;
    int level = pin_level(pin);
    race_lands();
    return level;
}

uint32_t host_reg_read(uint32_t reg)
{
    uint32_t v = 0;
    if (reg == GPIO_IN_REG)
        for (int pin = 0; pin < 32; pin++)
            v |= (uint32_t)pin_level(pin) << pin;
    race_lands();
    return v;
}

void attachInterruptArg(uint8_t pin, void (*handler)(void *), void *arg, int mode)
{
    if (pin >= N_GPIO)
        return;
    pins[pin].isr = handler;
    pins[pin].isr_arg = arg;
    pins[pin].isr_mode = mode;
}

static void run_isr(int pin, int level)
{
    pin_state *p = &pins[pin];
    if (p->isr && (p->isr_mode == CHANGE || (p->isr_mode == RISING && level) || (p->isr_mode == FALLING && !level)))
        p->isr(p->isr_arg);
}

/* the outside world drives an input pin: PCNT counts the edge, then the pin's interrupt runs */
static void drive_input(int pin, int level)
{
    if (pins[pin].in == level)
        return;
    pins[pin].in = (uint8_t)level;
    pcnt_edge(pin, level);
    run_isr(pin, level);
}

/* ---- PCNT (ESP-IDF 5.x pulse_cnt.c; ESP32-S3 TRM "Pulse Count Controller") -----------------------
 * Four units (SOC_PCNT_UNITS_PER_GROUP), two channels each; limits within the 16-bit signed counter,
 * low < 0 < high; the glitch filter at most 1023 APB cycles (12787 ns); channels and the filter only
 * while the unit is in its init state; a watch point within the limits, each once. At a limit the
 * counter returns to 0; with accum_count and a watch point on that limit the driver adds the limit to
 * its accumulator, so pcnt_unit_get_count goes on; without them the count is lost. */

struct host_pcnt_channel {
    int used, edge_gpio, level_gpio;
    pcnt_channel_edge_action_t pos, neg;
    pcnt_channel_level_action_t high, low;
};
struct host_pcnt_unit {
    int used, low, high, accum_on, state;  /* state: 0 init, 1 enabled, 2 running */
    int count, accum, watch[4], n_watch;
    host_pcnt_channel chan[2];
};
static host_pcnt_unit pcnt_units[4];

esp_err_t pcnt_new_unit(const pcnt_unit_config_t *config, pcnt_unit_handle_t *ret_unit)
{
    spend(DRIVER_CALL_US);
    if (!config || !ret_unit || !(config->low_limit < 0 && config->high_limit > 0 && config->low_limit >= -32768
                                  && config->high_limit <= 32767))
        return ESP_ERR_INVALID_ARG;
    for (int i = 0; i < 4; i++)
        if (!pcnt_units[i].used) {
            memset(&pcnt_units[i], 0, sizeof pcnt_units[i]);
            pcnt_units[i].used = 1;
            pcnt_units[i].low = config->low_limit;
            pcnt_units[i].high = config->high_limit;
            pcnt_units[i].accum_on = config->flags.accum_count;
            *ret_unit = &pcnt_units[i];
            return ESP_OK;
        }
    return ESP_ERR_NOT_FOUND;
}

esp_err_t pcnt_unit_set_glitch_filter(pcnt_unit_handle_t unit, const pcnt_glitch_filter_config_t *config)
{
    if (!unit)
        return ESP_ERR_INVALID_ARG;
    if (unit->state != 0)
        return ESP_ERR_INVALID_STATE;
    if (config && (uint64_t)config->max_glitch_ns * APB_HZ / 1000000000u > 1023u)
        return ESP_ERR_INVALID_ARG;
    return ESP_OK;
}

esp_err_t pcnt_new_channel(pcnt_unit_handle_t unit, const pcnt_chan_config_t *config, pcnt_channel_handle_t *ret_chan)
{
    if (!unit || !config || !ret_chan)
        return ESP_ERR_INVALID_ARG;
    if (unit->state != 0)
        return ESP_ERR_INVALID_STATE;
    for (int i = 0; i < 2; i++)
        if (!unit->chan[i].used) {
            host_pcnt_channel *c = &unit->chan[i];
            memset(c, 0, sizeof *c);
            c->used = 1;
            c->edge_gpio = config->edge_gpio_num;
            c->level_gpio = config->level_gpio_num;
            *ret_chan = c;
            return ESP_OK;
        }
    return ESP_ERR_NOT_FOUND;
}

esp_err_t pcnt_channel_set_edge_action(pcnt_channel_handle_t chan, pcnt_channel_edge_action_t pos_act,
                                       pcnt_channel_edge_action_t neg_act)
{
    if (!chan)
        return ESP_ERR_INVALID_ARG;
    chan->pos = pos_act;
    chan->neg = neg_act;
    return ESP_OK;
}

esp_err_t pcnt_channel_set_level_action(pcnt_channel_handle_t chan, pcnt_channel_level_action_t high_act,
                                        pcnt_channel_level_action_t low_act)
{
    if (!chan)
        return ESP_ERR_INVALID_ARG;
    chan->high = high_act;
    chan->low = low_act;
    return ESP_OK;
}

esp_err_t pcnt_unit_add_watch_point(pcnt_unit_handle_t unit, int watch_point)
{
    if (!unit || watch_point < unit->low || watch_point > unit->high)
        return ESP_ERR_INVALID_ARG;
    for (int i = 0; i < unit->n_watch; i++)
        if (unit->watch[i] == watch_point)
            return ESP_ERR_INVALID_STATE;
    if (unit->n_watch == 4)
        return ESP_ERR_NOT_FOUND;
    unit->watch[unit->n_watch++] = watch_point;
    return ESP_OK;
}

esp_err_t pcnt_unit_enable(pcnt_unit_handle_t unit)
{
    if (!unit)
        return ESP_ERR_INVALID_ARG;
    if (unit->state != 0)
        return ESP_ERR_INVALID_STATE;
    unit->state = 1;
    return ESP_OK;
}

esp_err_t pcnt_unit_clear_count(pcnt_unit_handle_t unit)
{
    if (!unit)
        return ESP_ERR_INVALID_ARG;
    unit->count = unit->accum = 0;
    return ESP_OK;
}

esp_err_t pcnt_unit_start(pcnt_unit_handle_t unit)
{
    if (!unit)
        return ESP_ERR_INVALID_ARG;
    if (unit->state != 1)
        return ESP_ERR_INVALID_STATE;
    unit->state = 2;
    return ESP_OK;
}

static int watched(const host_pcnt_unit *u, int value)
{
    for (int i = 0; i < u->n_watch; i++)
        if (u->watch[i] == value)
            return 1;
    return 0;
}

static uint64_t sampled_at[4096];   /* when the sketch read unit 0: its control tick's sampling instants */
static uint32_t n_sampled;

esp_err_t pcnt_unit_get_count(pcnt_unit_handle_t unit, int *value)
{
    if (!unit || !value)
        return ESP_ERR_INVALID_ARG;
    if (unit == &pcnt_units[0])
        sampled_at[n_sampled++ % 4096u] = now_us;
    *value = unit->count + (unit->accum_on ? unit->accum : 0);
    return ESP_OK;
}

static void pcnt_edge(int pin, int level)
{
    for (int u = 0; u < 4; u++) {
        host_pcnt_unit *unit = &pcnt_units[u];
        if (!unit->used || unit->state != 2)
            continue;
        for (int i = 0; i < 2; i++) {
            host_pcnt_channel *c = &unit->chan[i];
            if (!c->used || c->edge_gpio != pin)
                continue;
            pcnt_channel_edge_action_t act = level ? c->pos : c->neg;
            pcnt_channel_level_action_t lv = digitalRead((uint8_t)c->level_gpio) ? c->high : c->low;
            if (act == PCNT_CHANNEL_EDGE_ACTION_HOLD || lv == PCNT_CHANNEL_LEVEL_ACTION_HOLD)
                continue;
            int step = act == PCNT_CHANNEL_EDGE_ACTION_INCREASE ? 1 : -1;
            unit->count += lv == PCNT_CHANNEL_LEVEL_ACTION_INVERSE ? -step : step;
            if (unit->count == unit->high || unit->count == unit->low) {
                if (unit->accum_on && watched(unit, unit->count))
                    unit->accum += unit->count;
                unit->count = 0;
            }
        }
    }
}

/* ---- MCPWM (ESP-IDF 5.x mcpwm_timer.c, mcpwm_com.c, mcpwm_oper.c, mcpwm_cmpr.c, mcpwm_gen.c) -------
 * Two groups, each with three timers, three operators, two comparators and two generators per
 * operator. The group clock is the 160 MHz PLL divided by the group prescale (default 2, at most 256),
 * shared by the group's timers; a timer's prescale is at most 256 (mcpwm_set_prescale, else
 * ESP_ERR_INVALID_STATE); its period (up counting) 1 to 65535 ticks (peak_ticks < MCPWM_LL_MAX_COUNT_VALUE,
 * else ESP_ERR_INVALID_ARG); a compare value at most the peak. An operator works only with a timer of
 * its own group. A generator here follows the sketch's action pair or a forced level. */

#define MCPWM_SRC_HZ 160000000u
struct host_mcpwm_timer { int used, group, state; uint32_t period; };  /* state: 0 init, 1 enabled, 2 running */
struct host_mcpwm_oper { int used, group; host_mcpwm_timer *timer; int n_cmpr, n_gen; };
struct host_mcpwm_cmpr { int used; host_mcpwm_oper *oper; uint32_t value; };
struct host_mcpwm_gen {
    int used, gpio, force, invert;  /* force: -1 none, 0 low, 1 high (the generator's, before invert) */
    host_mcpwm_oper *oper;
    mcpwm_generator_action_t on_empty, on_compare;
    host_mcpwm_cmpr *cmpr;
};
static struct {
    uint32_t prescale;  /* 0: not set */
    host_mcpwm_timer timers[3];
    host_mcpwm_oper opers[3];
} mcpwm_groups[2];
static host_mcpwm_cmpr mcpwm_cmprs[2][6];
static host_mcpwm_gen mcpwm_gens[2][6];

esp_err_t mcpwm_new_timer(const mcpwm_timer_config_t *config, mcpwm_timer_handle_t *ret_timer)
{
    spend(DRIVER_CALL_US);
    if (!config || !ret_timer || config->group_id < 0 || config->group_id >= 2)
        return ESP_ERR_INVALID_ARG;
    uint32_t peak = config->count_mode == MCPWM_TIMER_COUNT_MODE_UP_DOWN ? config->period_ticks / 2 : config->period_ticks;
    if (!(peak > 0 && peak < 65536u) || config->resolution_hz == 0)
        return ESP_ERR_INVALID_ARG;
    int g = config->group_id;
    uint32_t group_prescale = mcpwm_groups[g].prescale ? mcpwm_groups[g].prescale : 2;
    uint32_t module = MCPWM_SRC_HZ / group_prescale / config->resolution_hz;
    if (!(module >= 1 && module <= 256)) {
        if (mcpwm_groups[g].prescale)
            return ESP_ERR_INVALID_STATE;  /* the group's prescale is taken: "group prescale conflict" */
        for (group_prescale = 1; group_prescale <= 256; group_prescale++) {
            module = MCPWM_SRC_HZ / group_prescale / config->resolution_hz;
            if (module >= 1 && module <= 256)
                break;
        }
        if (group_prescale > 256)
            return ESP_ERR_INVALID_STATE;  /* "group clock cannot match the resolution" */
    }
    for (int i = 0; i < 3; i++) {
        host_mcpwm_timer *t = &mcpwm_groups[g].timers[i];
        if (!t->used) {
            mcpwm_groups[g].prescale = group_prescale;
            t->used = 1;
            t->group = g;
            t->state = 0;
            t->period = peak;
            *ret_timer = t;
            return ESP_OK;
        }
    }
    return ESP_ERR_NOT_FOUND;
}

esp_err_t mcpwm_timer_enable(mcpwm_timer_handle_t timer)
{
    if (!timer)
        return ESP_ERR_INVALID_ARG;
    if (timer->state != 0)
        return ESP_ERR_INVALID_STATE;
    timer->state = 1;
    return ESP_OK;
}

esp_err_t mcpwm_timer_start_stop(mcpwm_timer_handle_t timer, mcpwm_timer_start_stop_cmd_t command)
{
    if (!timer)
        return ESP_ERR_INVALID_ARG;
    if (timer->state == 0)
        return ESP_ERR_INVALID_STATE;
    integrate();
    timer->state = command == MCPWM_TIMER_START_NO_STOP ? 2 : 1;
    return ESP_OK;
}

esp_err_t mcpwm_new_operator(const mcpwm_operator_config_t *config, mcpwm_oper_handle_t *ret_oper)
{
    spend(DRIVER_CALL_US);
    if (!config || !ret_oper || config->group_id < 0 || config->group_id >= 2)
        return ESP_ERR_INVALID_ARG;
    for (int i = 0; i < 3; i++) {
        host_mcpwm_oper *o = &mcpwm_groups[config->group_id].opers[i];
        if (!o->used) {
            memset(o, 0, sizeof *o);
            o->used = 1;
            o->group = config->group_id;
            *ret_oper = o;
            return ESP_OK;
        }
    }
    return ESP_ERR_NOT_FOUND;
}

esp_err_t mcpwm_operator_connect_timer(mcpwm_oper_handle_t oper, mcpwm_timer_handle_t timer)
{
    if (!oper || !timer || oper->group != timer->group)
        return ESP_ERR_INVALID_ARG;
    oper->timer = timer;
    return ESP_OK;
}

esp_err_t mcpwm_new_comparator(mcpwm_oper_handle_t oper, const mcpwm_comparator_config_t *config,
                               mcpwm_cmpr_handle_t *ret_cmpr)
{
    spend(DRIVER_CALL_US);
    if (!oper || !config || !ret_cmpr)
        return ESP_ERR_INVALID_ARG;
    if (oper->n_cmpr == 2)
        return ESP_ERR_NOT_FOUND;
    host_mcpwm_oper *base = mcpwm_groups[oper->group].opers;
    host_mcpwm_cmpr *c = &mcpwm_cmprs[oper->group][(oper - base) * 2 + oper->n_cmpr++];
    c->used = 1;
    c->oper = oper;
    c->value = 0;
    *ret_cmpr = c;
    return ESP_OK;
}

esp_err_t mcpwm_comparator_set_compare_value(mcpwm_cmpr_handle_t cmpr, uint32_t cmp_ticks)
{
    if (!cmpr)
        return ESP_ERR_INVALID_ARG;
    if (!cmpr->oper->timer)
        return ESP_ERR_INVALID_STATE;  /* "timer and operator are not connected" */
    if (cmp_ticks > cmpr->oper->timer->period)
        return ESP_ERR_INVALID_ARG;
    integrate();
    cmpr->value = cmp_ticks;
    return ESP_OK;
}

esp_err_t mcpwm_new_generator(mcpwm_oper_handle_t oper, const mcpwm_generator_config_t *config,
                              mcpwm_gen_handle_t *ret_gen)
{
    if (!oper || !config || !ret_gen || config->gen_gpio_num < 0 || config->gen_gpio_num >= N_GPIO)
        return ESP_ERR_INVALID_ARG;
    if (oper->n_gen == 2)
        return ESP_ERR_NOT_FOUND;
    host_mcpwm_oper *base = mcpwm_groups[oper->group].opers;
    host_mcpwm_gen *g = &mcpwm_gens[oper->group][(oper - base) * 2 + oper->n_gen++];
    spend(DRIVER_CALL_US);
    memset(g, 0, sizeof *g);
    g->used = 1;
    g->oper = oper;
    g->gpio = config->gen_gpio_num;
    g->force = -1;
    g->invert = config->flags.invert_pwm;  /* in the GPIO matrix (esp_rom_gpio_connect_out_signal): every level */
    pins[g->gpio].gen = g;
    pins[g->gpio].mode = OUTPUT;
    *ret_gen = g;
    return ESP_OK;
}

esp_err_t mcpwm_generator_set_force_level(mcpwm_gen_handle_t gen, int level, bool hold_on)
{
    if (!gen || level < -1 || level > 1 || (level == -1 && !hold_on))
        return ESP_ERR_INVALID_ARG;
    integrate();
    gen->force = level;
    return ESP_OK;
}

esp_err_t mcpwm_generator_set_action_on_timer_event(mcpwm_gen_handle_t gen, mcpwm_gen_timer_event_action_t ev)
{
    if (!gen || ev.event != MCPWM_TIMER_EVENT_EMPTY || ev.direction != MCPWM_TIMER_DIRECTION_UP)
        return ESP_ERR_INVALID_ARG;  /* up counting: the period starts at EMPTY; FULL is its end */
    integrate();
    gen->on_empty = ev.action;
    return ESP_OK;
}

esp_err_t mcpwm_generator_set_action_on_compare_event(mcpwm_gen_handle_t gen, mcpwm_gen_compare_event_action_t ev)
{
    if (!gen || !ev.comparator || ev.comparator->oper != gen->oper || ev.direction != MCPWM_TIMER_DIRECTION_UP)
        return ESP_ERR_INVALID_ARG;
    integrate();
    gen->on_compare = ev.action;
    gen->cmpr = ev.comparator;
    return ESP_OK;
}

/* The share of one PWM period a generator's output is high, as the interval [lo, hi) of the period. */
static void generator_interval(const host_mcpwm_gen *g, double *lo, double *hi)
{
    const host_mcpwm_timer *t = g->oper->timer;
    *lo = 0.0;
    *hi = 0.0;
    if (g->force >= 0) {
        *hi = g->force ? 1.0 : 0.0;
        return;
    }
    if (!t || t->state != 2 || !g->cmpr)
        return;  /* no timer running: the generator holds its reset level, low */
    double c = (double)(g->cmpr->value < t->period ? g->cmpr->value : t->period) / (double)t->period;
    if (g->on_empty == MCPWM_GEN_ACTION_LOW && g->on_compare == MCPWM_GEN_ACTION_HIGH) {
        *lo = c;
        *hi = 1.0;
    } else if (g->on_empty == MCPWM_GEN_ACTION_HIGH && g->on_compare == MCPWM_GEN_ACTION_LOW) {
        *hi = c;
    }
}

/* The share of one PWM period a pin is high, as the interval [lo, hi) of the period. */
static void high_interval(int pin, double *lo, double *hi)
{
    const pin_state *p = &pins[pin];
    *lo = 0.0;
    *hi = 0.0;
    if (p->gen) {
        generator_interval(p->gen, lo, hi);
        if (p->gen->invert) {  /* the complement of [lo, hi), one interval for the actions above */
            double a = *lo, b = *hi;
            *lo = a > 0.0 ? 0.0 : b;
            *hi = a > 0.0 ? a : 1.0;
        }
        return;
    }
    if (p->mode == OUTPUT)
        *hi = p->out ? 1.0 : 0.0;
    else  /* an input or an unset pin: the board's pull-up against the DRV8833's pull-down (100 kOhm) */
        *hi = p->pull_up ? 1.0 : 0.0;
}

/* ---- the H-bridges (TI DRV8833 datasheet, table "H-bridge logic"): time in each state per motor ---- */

struct motor_wiring { int used, in1, in2, enc_a, enc_b; int64_t position; };
static motor_wiring motors[N_MOTORS];
static double bridge_time[N_MOTORS][4];  /* us forward (IN1 1 IN2 0), reverse (0 1), brake (1 1), coast (0 0) */
static uint64_t integrated_to;

static void integrate(void)
{
    double dt = (double)(now_us - integrated_to);
    integrated_to = now_us;
    if (dt <= 0.0)
        return;
    for (int k = 0; k < N_MOTORS; k++) {
        if (!motors[k].used)
            continue;
        double a0, a1, b0, b1;
        high_interval(motors[k].in1, &a0, &a1);
        high_interval(motors[k].in2, &b0, &b1);
        double lo = a0 > b0 ? a0 : b0, hi = a1 < b1 ? a1 : b1;
        double both = hi > lo ? hi - lo : 0.0, h1 = a1 - a0, h2 = b1 - b0;
        bridge_time[k][0] += dt * (h1 - both);
        bridge_time[k][1] += dt * (h2 - both);
        bridge_time[k][2] += dt * both;
        bridge_time[k][3] += dt * (1.0 - h1 - h2 + both);
    }
}

/* ---- timer (esp32-hal-timer.c on the GPTimer driver: resolution = 80 MHz APB / a prescale of 2 to 65535) */

struct host_hw_timer { int used; uint32_t hz; void (*isr)(void); uint64_t period_us, next_us; int armed; };
static host_hw_timer hw_timers[4];

hw_timer_t *timerBegin(uint32_t frequency)
{
    if (frequency == 0 || APB_HZ / frequency < 2 || APB_HZ / frequency > 65535)
        return NULL;
    for (int i = 0; i < 4; i++)
        if (!hw_timers[i].used) {
            memset(&hw_timers[i], 0, sizeof hw_timers[i]);
            hw_timers[i].used = 1;
            hw_timers[i].hz = frequency;
            return &hw_timers[i];
        }
    return NULL;
}

void timerAttachInterrupt(hw_timer_t *timer, void (*userFunc)(void))
{
    if (timer)
        timer->isr = userFunc;
}

void timerAlarm(hw_timer_t *timer, uint64_t alarm_value, bool autoreload, uint64_t reload_count)
{
    (void)reload_count;
    if (!timer || alarm_value == 0)
        return;
    timer->period_us = alarm_value * 1000000u / timer->hz;
    timer->next_us = now_us + timer->period_us;
    timer->armed = autoreload ? 2 : 1;
}

/* ---- ADC (esp32-hal-adc.c analogReadMilliVolts, calibrated; ESP32-S3 datasheet: ADC1 on GPIO1-10, with
 * 11 dB (12 dB) attenuation it measures 0 to about 3100 mV) ------------------------------------------ */

static uint32_t pin_mv[N_GPIO];
void analogSetPinAttenuation(uint8_t pin, adc_attenuation_t attenuation) { (void)pin; (void)attenuation; }
uint32_t analogReadMilliVolts(uint8_t pin)
{
    if (pin < 1 || pin > 20)
        return 0;  /* not an ADC pin */
    return pin_mv[pin] < 3100u ? pin_mv[pin] : 3100u;
}

/* ---- HWCDC (cores/esp32/HWCDC.cpp): the USB Serial/JTAG port. Receive buffer 256 bytes unless
 * setRxBufferSize; transmit ring 256 bytes; write() waits up to tx_timeout_ms (100 ms unless
 * setTxTimeoutMs) for room while the host is connected, then gives up on the rest. ---------------- */

#define CDC_TX_CAP 256u
#define CDC_MAX_RX 65536u
static uint8_t cdc_rx[CDC_MAX_RX], cdc_tx[CDC_TX_CAP];
static size_t cdc_rx_cap = 256, cdc_rx_len, cdc_tx_len;
static uint32_t cdc_tx_timeout_ms = 100;
static uint64_t cdc_blocked_us;  /* time writes spent waiting */

HWCDC Serial;
size_t HWCDC::setRxBufferSize(size_t size)
{
    if (size == 0 || size > CDC_MAX_RX)
        return 0;
    cdc_rx_cap = size;
    return size;
}
void HWCDC::setTxTimeoutMs(uint32_t timeout) { cdc_tx_timeout_ms = timeout; }
void HWCDC::begin(unsigned long baud)
{
    (void)baud;
    spend(DRIVER_CALL_US);
}
int HWCDC::available(void) { return (int)cdc_rx_len; }
size_t HWCDC::read(uint8_t *buffer, size_t size)
{
    size_t n = size < cdc_rx_len ? size : cdc_rx_len;
    memcpy(buffer, cdc_rx, n);
    memmove(cdc_rx, cdc_rx + n, cdc_rx_len - n);
    cdc_rx_len -= n;
    return n;
}
int HWCDC::availableForWrite(void) { return (int)(CDC_TX_CAP - cdc_tx_len); }
size_t HWCDC::write(const uint8_t *buffer, size_t size)
{
    size_t room = CDC_TX_CAP - cdc_tx_len, n = size < room ? size : room;
    memcpy(cdc_tx + cdc_tx_len, buffer, n);
    cdc_tx_len += n;
    if (n < size && cdc_tx_timeout_ms) {  /* the host reads nothing while the write waits */
        now_us += (uint64_t)cdc_tx_timeout_ms * 1000u;
        cdc_blocked_us += (uint64_t)cdc_tx_timeout_ms * 1000u;
    }
    return n;
}

/* ---- reset reason, task watchdog (esp32-hal-misc.c enableLoopWDT: loopTask on the TWDT, reset in
 * every pass of loop(); CONFIG_ESP_TASK_WDT_TIMEOUT_S = 5 in Arduino's build) ----------------------- */

esp_reset_reason_t esp_reset_reason(void) { return reset_reason; }
static int loop_wdt;
static int wdt_expired;
void enableLoopWDT(void) { loop_wdt = 1; }
#define TWDT_TIMEOUT_US 5000000u
static uint64_t loop_returned_us;  /* when loop() last returned: the TWDT's last reset */
static uint64_t hung_until_us;     /* host_hang_loop: loop() does not return before this */

/* ---- NVS through Preferences (libraries/Preferences; ESP-IDF 5.x "Non-Volatile Storage Library": 4096-byte
 * flash pages): one page of key/blob records the host keeps across resets
 * (host_nvs_dump / host_nvs_load), as the flash keeps them across power cycles ---------------------- */

#define NVS_BYTES 4096u
static uint8_t nvs[NVS_BYTES];  /* records: key[16], length u16, bytes */
static size_t nvs_used;

static uint8_t *nvs_find(const char *key, size_t *len)
{
    for (size_t at = 0; at + 18 <= nvs_used;) {
        size_t n = (size_t)(nvs[at + 16] | nvs[at + 17] << 8);
        if (strncmp((const char *)nvs + at, key, 16) == 0) {
            *len = n;
            return nvs + at + 18;
        }
        at += 18 + n;
    }
    return NULL;
}

bool Preferences::begin(const char *name, bool readOnly)
{
    open_ = name && strlen(name) <= 15;
    read_only_ = readOnly;
    return open_;
}
void Preferences::end(void) { open_ = false; }
size_t Preferences::getBytesLength(const char *key)
{
    size_t n = 0;
    return open_ && nvs_find(key, &n) ? n : 0;
}
size_t Preferences::getBytes(const char *key, void *buf, size_t len)
{
    size_t n = 0;
    uint8_t *at = open_ ? nvs_find(key, &n) : NULL;
    if (!at || n > len)
        return 0;
    memcpy(buf, at, n);
    return n;
}
size_t Preferences::putBytes(const char *key, const void *value, size_t len)
{
    size_t n = 0;
    if (!open_ || read_only_ || strlen(key) > 15 || len > 0xFFFF)
        return 0;
    uint8_t *at = nvs_find(key, &n);
    if (at && n == len) {
        memcpy(at, value, len);
        return len;
    }
    if (at) {  /* remove the old record, then append */
        size_t start = (size_t)(at - 18 - nvs), end = start + 18 + n;
        memmove(nvs + start, nvs + end, nvs_used - end);
        nvs_used -= end - start;
    }
    if (nvs_used + 18 + len > NVS_BYTES)
        return 0;  /* the page is full: ESP_ERR_NVS_NOT_ENOUGH_SPACE */
    memset(nvs + nvs_used, 0, 16);
    strncpy((char *)nvs + nvs_used, key, 16);
    nvs[nvs_used + 16] = (uint8_t)(len & 0xFF);
    nvs[nvs_used + 17] = (uint8_t)(len >> 8);
    memcpy(nvs + nvs_used + 18, value, len);
    nvs_used += 18 + len;
    return len;
}

/* ---- the plant's side (controllers/sketch.py) -------------------------------------------------------- */

extern "C" {

/* Motor k's wiring: its bridge inputs and encoder outputs (GPIO numbers), its shaft at `position` counts. */
void host_connect_motor(int k, int in1, int in2, int enc_a, int enc_b, int64_t position)
{
    static const uint8_t AB[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};  /* A leads B as the count rises */
    motor_wiring *m = &motors[k];
    m->used = 1;
    m->in1 = in1;
    m->in2 = in2;
    m->enc_a = enc_a;
    m->enc_b = enc_b;
    m->position = position;
    int phase = (int)(((position % 4) + 4) % 4);
    if (enc_a >= 0)
        pins[enc_a].in = AB[phase][0];
    if (enc_b >= 0)
        pins[enc_b].in = AB[phase][1];
}

/* Turn motor k's shaft to `position` counts: every quadrature edge on the way, in order. */
void host_set_encoder(int k, int64_t position)
{
    static const uint8_t AB[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
    motor_wiring *m = &motors[k];
    while (m->position != position) {
        m->position += position > m->position ? 1 : -1;
        int phase = (int)(((m->position % 4) + 4) % 4);
        if (m->enc_a >= 0 && pins[m->enc_a].in != AB[phase][0])
            drive_input(m->enc_a, AB[phase][0]);
        if (m->enc_b >= 0 && pins[m->enc_b].in != AB[phase][1])
            drive_input(m->enc_b, AB[phase][1]);
    }
}

/* Turn motor k's shaft to `position` counts with each edge landing while the interrupt of the one before it
 * reads its inputs (edges closer than an interrupt's latency): a decoder that reads A and B apart sees a
 * state that never was. */
void host_set_encoder_racing(int k, int64_t position)
{
    static const uint8_t AB[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
    motor_wiring *m = &motors[k];
    while (m->position != position) {
        int64_t next = m->position + (position > m->position ? 1 : -1);
        int phase = (int)(((next % 4) + 4) % 4);
        int pin = pins[m->enc_a].in != AB[phase][0] ? m->enc_a : m->enc_b;
        int level = pin == m->enc_a ? AB[phase][0] : AB[phase][1];
        m->position = next;
        if (isr_pending < 0 && race_pin < 0) {  /* the first edge: lands at once */
            pins[pin].in = (uint8_t)level;
            pcnt_edge(pin, level);
            isr_pending = pin;
            continue;
        }
        race_pin = pin;  /* lands during the pending edge's interrupt */
        race_level = level;
        int p = isr_pending;
        isr_pending = -1;
        run_isr(p, pins[p].in);
        if (race_pin >= 0) {  /* the interrupt read nothing: it lands after */
            race_lands();
        }
    }
    while (isr_pending >= 0) {
        int p = isr_pending;
        isr_pending = -1;
        run_isr(p, pins[p].in);
    }
}

/* Motor k's encoder outputs both flip at once (a glitch, or two edges inside one interrupt's latency): A's
 * interrupt, then B's, run after both have changed. */
void host_encoder_glitch(int k)
{
    motor_wiring *m = &motors[k];
    const int both[2] = {m->enc_a, m->enc_b};
    for (int pin : both) {
        pins[pin].in ^= 1;
        pcnt_edge(pin, pins[pin].in);
    }
    run_isr(m->enc_a, pins[m->enc_a].in);
    run_isr(m->enc_b, pins[m->enc_b].in);
}

void host_set_pin_mv(int pin, uint32_t mv)
{
    if (pin >= 0 && pin < N_GPIO)
        pin_mv[pin] = mv;
}

/* The board's own pull-up on a pin (a resistor to 3.3 V), there from power-on. */
void host_pull_up(int pin, int on)
{
    if (pin >= 0 && pin < N_GPIO)
        pins[pin].pull_up = (uint8_t)(on != 0);
}

/* Start the board at at_us: the reset reason it will report, ROM_BOOT_US with every pin an input (the ROM,
 * the bootloader), then setup(), whose calls take their time. */
void host_boot(int reason, uint64_t at_us)
{
    now_us = integrated_to = at_us;
    reset_reason = (esp_reset_reason_t)reason;
    spend(ROM_BOOT_US);
    setup();
    loop_returned_us = now_us;
}

/* Run the board for `us` microseconds: the timer's interrupts when due, loop() after each (and once
 * more per interrupt that fired while it was busy), the task watchdog. Returns 1 once the watchdog fired. */
int host_advance(uint32_t us)
{
    uint64_t end = now_us + us;
    while (now_us < end && !wdt_expired) {
        int fired = 0;
        uint64_t next = end;
        for (int i = 0; i < 4; i++) {
            host_hw_timer *t = &hw_timers[i];
            while (t->used && t->armed && t->isr && t->next_us <= now_us) {
                t->isr();
                fired++;
                t->next_us += t->period_us;
                if (t->armed == 1)
                    t->armed = 0;
            }
        }
        if (now_us >= hung_until_us) {
            for (int i = 0; i < (fired ? fired : 1); i++) {
                uint64_t before = now_us;
                loop();
                if (now_us - before > TWDT_TIMEOUT_US)
                    loop_returned_us = before;  /* this pass alone held it too long */
                else
                    loop_returned_us = now_us;
            }
        }
        if (loop_wdt && now_us - loop_returned_us > TWDT_TIMEOUT_US)
            wdt_expired = 1;
        for (int i = 0; i < 4; i++)
            if (hw_timers[i].used && hw_timers[i].armed && hw_timers[i].next_us < next)
                next = hw_timers[i].next_us;
        if (now_us < next) {
            integrate();
            now_us = next;
        }
    }
    integrate();
    return wdt_expired;
}

/* loop() hangs from now for `us` (a bug: a wait that never ends): the timer's interrupts go on, the task
 * watchdog counts from its last return. */
void host_hang_loop(uint32_t us)
{
    hung_until_us = now_us + us;
}

/* Motor k's bridge over the time since the last call: pwm in [-1, 1] (forward minus reverse share),
 * and whether any of it was braking or driving (1) rather than all coasting (0). */
void host_bridge(int k, float *pwm, uint8_t *decay, double *shares)
{
    integrate();
    double *t = bridge_time[k], total = t[0] + t[1] + t[2] + t[3];
    if (total <= 0.0) {
        *pwm = 0.0f;
        *decay = 0;
        return;
    }
    *pwm = (float)((t[0] - t[1]) / total);
    *decay = (uint8_t)(t[3] < total * 0.5 ? 1 : 0);
    for (int i = 0; i < 4; i++) {
        if (shares)
            shares[i] = t[i] / total;
        t[i] = 0.0;
    }
}

/* Bytes from the host into the receive buffer; returns how many fit. */
uint32_t host_rx(const uint8_t *data, uint32_t n)
{
    uint32_t room = (uint32_t)(cdc_rx_cap - cdc_rx_len), take = n < room ? n : room;
    memcpy(cdc_rx + cdc_rx_len, data, take);
    cdc_rx_len += take;
    return take;
}

/* Bytes the host reads from the transmit ring; returns how many. */
uint32_t host_tx(uint8_t *out, uint32_t max)
{
    uint32_t n = (uint32_t)(cdc_tx_len < max ? cdc_tx_len : max);
    memcpy(out, cdc_tx, n);
    memmove(cdc_tx, cdc_tx + n, cdc_tx_len - n);
    cdc_tx_len -= n;
    return n;
}

/* The flash's contents, to carry across a reset (host_nvs_load into the next instance before host_boot). */
uint32_t host_nvs_dump(uint8_t *out, uint32_t max)
{
    uint32_t n = (uint32_t)(nvs_used < max ? nvs_used : max);
    memcpy(out, nvs, n);
    return n;
}

void host_nvs_load(const uint8_t *data, uint32_t n)
{
    nvs_used = n < NVS_BYTES ? n : NVS_BYTES;
    memcpy(nvs, data, nvs_used);
}

uint64_t host_now_us(void) { return now_us; }
uint64_t host_blocked_us(void) { return cdc_blocked_us; }

/* The last `max` control-tick sampling instants (us), oldest first; returns how many. */
uint32_t host_sample_times(uint64_t *out, uint32_t max)
{
    uint32_t n = n_sampled < 4096u ? n_sampled : 4096u;
    if (n > max)
        n = max;
    for (uint32_t i = 0; i < n; i++)
        out[i] = sampled_at[(n_sampled - n + i) % 4096u];
    return n;
}

}  /* extern "C" */
