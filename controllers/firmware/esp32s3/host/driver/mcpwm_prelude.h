/* Host stand-in: ESP-IDF 5.x driver/mcpwm_prelude.h, the calls the sketch makes
 * (components/esp_driver_mcpwm/include/driver/; behaviour and limits in host/esp32s3_host.cpp). */
#ifndef HOST_MCPWM_PRELUDE_H
#define HOST_MCPWM_PRELUDE_H
#include <stdint.h>
#include "esp_err.h"

typedef struct host_mcpwm_timer *mcpwm_timer_handle_t;
typedef struct host_mcpwm_oper *mcpwm_oper_handle_t;
typedef struct host_mcpwm_cmpr *mcpwm_cmpr_handle_t;
typedef struct host_mcpwm_gen *mcpwm_gen_handle_t;

typedef enum { MCPWM_TIMER_CLK_SRC_PLL160M = 1, MCPWM_TIMER_CLK_SRC_DEFAULT = MCPWM_TIMER_CLK_SRC_PLL160M }
    mcpwm_timer_clock_source_t;
typedef enum { MCPWM_TIMER_COUNT_MODE_PAUSE, MCPWM_TIMER_COUNT_MODE_UP, MCPWM_TIMER_COUNT_MODE_DOWN,
               MCPWM_TIMER_COUNT_MODE_UP_DOWN } mcpwm_timer_count_mode_t;
typedef enum { MCPWM_TIMER_DIRECTION_UP, MCPWM_TIMER_DIRECTION_DOWN } mcpwm_timer_direction_t;
typedef enum { MCPWM_TIMER_EVENT_EMPTY, MCPWM_TIMER_EVENT_FULL, MCPWM_TIMER_EVENT_INVALID } mcpwm_timer_event_t;
typedef enum { MCPWM_GEN_ACTION_KEEP, MCPWM_GEN_ACTION_LOW, MCPWM_GEN_ACTION_HIGH, MCPWM_GEN_ACTION_TOGGLE }
    mcpwm_generator_action_t;
typedef enum { MCPWM_TIMER_STOP_EMPTY, MCPWM_TIMER_STOP_FULL, MCPWM_TIMER_START_NO_STOP, MCPWM_TIMER_START_STOP_EMPTY,
               MCPWM_TIMER_START_STOP_FULL } mcpwm_timer_start_stop_cmd_t;

typedef struct {
    int group_id;
    mcpwm_timer_clock_source_t clk_src;
    uint32_t resolution_hz;
    mcpwm_timer_count_mode_t count_mode;
    uint32_t period_ticks;
    int intr_priority;
    struct { uint32_t update_period_on_empty : 1, update_period_on_sync : 1; } flags;
} mcpwm_timer_config_t;

typedef struct {
    int group_id;
    int intr_priority;
    struct { uint32_t update_gen_action_on_tez : 1, update_gen_action_on_tep : 1, update_gen_action_on_sync : 1,
             update_dead_time_on_tez : 1, update_dead_time_on_tep : 1, update_dead_time_on_sync : 1; } flags;
} mcpwm_operator_config_t;

typedef struct {
    int intr_priority;
    struct { uint32_t update_cmp_on_tez : 1, update_cmp_on_tep : 1, update_cmp_on_sync : 1; } flags;
} mcpwm_comparator_config_t;

typedef struct {
    int gen_gpio_num;
    struct { uint32_t invert_pwm : 1, io_loop_back : 1, io_od_mode : 1, pull_up : 1, pull_down : 1; } flags;
} mcpwm_generator_config_t;

typedef struct { mcpwm_timer_direction_t direction; mcpwm_timer_event_t event; mcpwm_generator_action_t action; }
    mcpwm_gen_timer_event_action_t;
typedef struct { mcpwm_timer_direction_t direction; mcpwm_cmpr_handle_t comparator; mcpwm_generator_action_t action; }
    mcpwm_gen_compare_event_action_t;

#define MCPWM_GEN_TIMER_EVENT_ACTION(dir, ev, act) (mcpwm_gen_timer_event_action_t){dir, ev, act}
#define MCPWM_GEN_COMPARE_EVENT_ACTION(dir, cmp, act) (mcpwm_gen_compare_event_action_t){dir, cmp, act}

esp_err_t mcpwm_new_timer(const mcpwm_timer_config_t *config, mcpwm_timer_handle_t *ret_timer);
esp_err_t mcpwm_timer_enable(mcpwm_timer_handle_t timer);
esp_err_t mcpwm_timer_start_stop(mcpwm_timer_handle_t timer, mcpwm_timer_start_stop_cmd_t command);
esp_err_t mcpwm_new_operator(const mcpwm_operator_config_t *config, mcpwm_oper_handle_t *ret_oper);
esp_err_t mcpwm_operator_connect_timer(mcpwm_oper_handle_t oper, mcpwm_timer_handle_t timer);
esp_err_t mcpwm_new_comparator(mcpwm_oper_handle_t oper, const mcpwm_comparator_config_t *config,
                               mcpwm_cmpr_handle_t *ret_cmpr);
esp_err_t mcpwm_comparator_set_compare_value(mcpwm_cmpr_handle_t cmpr, uint32_t cmp_ticks);
esp_err_t mcpwm_new_generator(mcpwm_oper_handle_t oper, const mcpwm_generator_config_t *config,
                              mcpwm_gen_handle_t *ret_gen);
esp_err_t mcpwm_generator_set_force_level(mcpwm_gen_handle_t gen, int level, bool hold_on);
esp_err_t mcpwm_generator_set_action_on_timer_event(mcpwm_gen_handle_t gen, mcpwm_gen_timer_event_action_t ev_act);
esp_err_t mcpwm_generator_set_action_on_compare_event(mcpwm_gen_handle_t gen, mcpwm_gen_compare_event_action_t ev_act);
#endif
