/* Host stand-in: ESP-IDF 5.x driver/gpio.h, the one call the sketch makes (components/esp_driver_gpio:
 * gpio_set_level writes the pin's output register, whatever the pin's direction; behaviour in
 * host/esp32s3_host.cpp). */
#ifndef HOST_DRIVER_GPIO_H
#define HOST_DRIVER_GPIO_H
#include <stdint.h>
#include "esp_err.h"

typedef int gpio_num_t;
esp_err_t gpio_set_level(gpio_num_t gpio_num, uint32_t level);
#endif
