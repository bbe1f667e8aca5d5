/* Host stand-in: Arduino-ESP32 3.x Preferences (libraries/Preferences, on ESP-IDF's NVS): named blobs in a
 * namespace that survive a reset and a power cycle. Keys at most 15 characters (NVS_KEY_NAME_MAX_SIZE - 1). */
#ifndef HOST_PREFERENCES_H
#define HOST_PREFERENCES_H
#include <stddef.h>

class Preferences {
  public:
    bool begin(const char *name, bool readOnly = false);
    void end(void);
    size_t getBytesLength(const char *key);
    size_t getBytes(const char *key, void *buf, size_t len);
    size_t putBytes(const char *key, const void *value, size_t len);

  private:
    bool open_ = false, read_only_ = false;
};
#endif
