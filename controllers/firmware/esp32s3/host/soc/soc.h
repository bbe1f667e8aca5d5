/* Host stand-in: ESP-IDF 5.x soc/soc.h, REG_READ (components/soc/esp32s3/include/soc/soc.h): a register read,
 * here the stand-ins' (host/esp32s3_host.cpp host_reg_read: GPIO_IN_REG only). */
#ifndef HOST_SOC_SOC_H
#define HOST_SOC_SOC_H
#include <stdint.h>
uint32_t host_reg_read(uint32_t reg);
#define REG_READ(reg) host_reg_read(reg)
#endif
