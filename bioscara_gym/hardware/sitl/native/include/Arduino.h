/*
 * Arduino.h for the host build of the joint firmware (bioscara_gym SITL).
 *
 * The project's own stand-in: only what the joint firmware uses of the
 * STM32 Arduino core (millis, delay, Serial), with time following the
 * simulated clock (runtime.cpp). Standard headers the core brings in on the
 * chip (string, math, limits) are included here for the same reason.
 */
#ifndef BIOSCARA_SITL_ARDUINO_H
#define BIOSCARA_SITL_ARDUINO_H

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#include <cmath>
#include <cstdlib>
#include <limits>

/* abs() of a float is the float's magnitude on the chip (the core's abs), as here. */
using std::abs;

typedef bool boolean;
typedef uint8_t byte;

#define DEC 10
#define HEX 16
#define OCT 8
#define BIN 2

uint32_t millis(void);
uint32_t micros(void);
void delay(uint32_t ms);
void delayMicroseconds(uint32_t us);
void yield(void);

/* The sketch's entry points (Arduino calls setup() once, then loop() forever). */
void setup(void);
void loop(void);

/* Serial output: formatted like the Arduino core's Print, kept only while captured. */
class Print {
  public:
    size_t write(uint8_t c);
    size_t write(const char *s);
    size_t write(const uint8_t *buffer, size_t size);

    size_t print(const char *s);
    size_t print(char c);
    size_t print(unsigned char n, int base = DEC);
    size_t print(int n, int base = DEC);
    size_t print(unsigned int n, int base = DEC);
    size_t print(long n, int base = DEC);
    size_t print(unsigned long n, int base = DEC);
    size_t print(long long n, int base = DEC);
    size_t print(unsigned long long n, int base = DEC);
    size_t print(double n, int digits = 2);

    size_t println(void);
    size_t println(const char *s);
    size_t println(char c);
    size_t println(unsigned char n, int base = DEC);
    size_t println(int n, int base = DEC);
    size_t println(unsigned int n, int base = DEC);
    size_t println(long n, int base = DEC);
    size_t println(unsigned long n, int base = DEC);
    size_t println(long long n, int base = DEC);
    size_t println(unsigned long long n, int base = DEC);
    size_t println(double n, int digits = 2);

    size_t printf(const char *format, ...) __attribute__((format(printf, 2, 3)));

  private:
    size_t printNumber(unsigned long long n, int base, bool negative);
};

class HardwareSerial : public Print {
  public:
    void begin(unsigned long baud);
    void end(void);
    int available(void);
    int read(void);
    void flush(void);
    operator bool() { return true; }
};

extern HardwareSerial Serial;

#endif
