/* Host stand-in: the Arduino-ESP32 3.x calls the sketch makes (cores/esp32: esp32-hal-gpio.h,
 * esp32-hal-timer.h, esp32-hal-adc.h, HWCDC.h, esp32-hal-misc's enableLoopWDT). Behaviour, limits and
 * their sources are in host/esp32s3_host.cpp; nothing here runs on silicon. */
#ifndef HOST_ARDUINO_H
#define HOST_ARDUINO_H
#include <stddef.h>
#include <stdint.h>
#include "esp_err.h"

#define IRAM_ATTR
#define HIGH 1
#define LOW 0
#define INPUT 0x01
#define OUTPUT 0x03
#define INPUT_PULLUP 0x05
#define RISING 0x01
#define FALLING 0x02
#define CHANGE 0x03

typedef enum { ADC_0db, ADC_2_5db, ADC_6db, ADC_11db } adc_attenuation_t;
typedef struct host_hw_timer hw_timer_t;

void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t val);
int digitalRead(uint8_t pin);
void attachInterruptArg(uint8_t pin, void (*handler)(void *), void *arg, int mode);
unsigned long micros(void);
void analogSetPinAttenuation(uint8_t pin, adc_attenuation_t attenuation);
uint32_t analogReadMilliVolts(uint8_t pin);
hw_timer_t *timerBegin(uint32_t frequency);
void timerAttachInterrupt(hw_timer_t *timer, void (*userFunc)(void));
void timerAlarm(hw_timer_t *timer, uint64_t alarm_value, bool autoreload, uint64_t reload_count);
void enableLoopWDT(void);

/* HWCDC: the ESP32-S3's USB Serial/JTAG port, `Serial` with ARDUINO_USB_MODE=1 and ARDUINO_USB_CDC_ON_BOOT=1 */
class HWCDC {
  public:
    size_t setRxBufferSize(size_t size);
    void setTxTimeoutMs(uint32_t timeout);
    void begin(unsigned long baud);
    int available(void);
    size_t read(uint8_t *buffer, size_t size);
    int availableForWrite(void);
    size_t write(const uint8_t *buffer, size_t size);
};
extern HWCDC Serial;
#endif
