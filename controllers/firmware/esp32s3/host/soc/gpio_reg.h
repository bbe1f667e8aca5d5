/* Host stand-in: ESP-IDF 5.x soc/gpio_reg.h for the ESP32-S3 (components/soc/esp32s3/include/soc/gpio_reg.h):
 * GPIO_IN_REG, the input levels of GPIO0-31 in one word (DR_REG_GPIO_BASE 0x60004000 + 0x3C). */
#ifndef HOST_SOC_GPIO_REG_H
#define HOST_SOC_GPIO_REG_H
#define GPIO_IN_REG 0x6000403Cu
#endif
