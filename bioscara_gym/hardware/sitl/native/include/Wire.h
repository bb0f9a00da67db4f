/*
 * Wire.h for the host build of the joint firmware (bioscara_gym SITL).
 *
 * The project's own stand-in for the Arduino Wire library as an I2C
 * follower: begin(address), onReceive/onRequest, read/available in the
 * receive handler, write in the request handler. The handlers run when the
 * host's emulated bus delivers a transaction (runtime.cpp), between the
 * firmware's own steps, as the interrupts do on the chip.
 */
#ifndef BIOSCARA_SITL_WIRE_H
#define BIOSCARA_SITL_WIRE_H

#include <Arduino.h>

/* The Arduino core's I2C buffer size. */
#define BUFFER_LENGTH 32

class TwoWire {
  public:
    void begin(void);
    void begin(uint8_t address);
    void begin(int address);
    void onReceive(void (*handler)(int));
    void onRequest(void (*handler)(void));
    int available(void);
    int read(void);
    int peek(void);
    size_t write(uint8_t data);
    size_t write(const uint8_t *data, size_t quantity);
    void setClock(uint32_t hz);
};

extern TwoWire Wire;

#endif
