/*
 * The Arduino core's functions the joint firmware uses, for the host build
 * (bioscara_gym SITL): time follows the simulated clock, Serial is captured,
 * Wire is an I2C follower fed by the host's emulated bus.
 */
#include <Arduino.h>
#include <Wire.h>
#include <stdarg.h>
#include <stdio.h>

#include "sitl.h"

using sitl::rt;

HardwareSerial Serial;
TwoWire Wire;

// ---------------------------------------------------------------- time

uint32_t millis(void) {
    sitl::spin();
    int64_t us = rt.in_isr ? rt.isr_us : rt.now_us;
    return (uint32_t)(us / 1000);
}

uint32_t micros(void) {
    sitl::spin();
    int64_t us = rt.in_isr ? rt.isr_us : rt.now_us;
    return (uint32_t)us;
}

void delay(uint32_t ms) {
    if (ms == 0) {
        return;
    }
    sitl::wait_ms(ms);
}

void delayMicroseconds(uint32_t us) {
    /* Time passes in whole milliseconds: a wait of less than one is not seen. */
    if (us >= 1000) {
        sitl::wait_ms(us / 1000);
    }
}

void yield(void) {}

// -------------------------------------------------------------- serial

size_t Print::write(uint8_t c) {
    char ch = (char)c;
    sitl::serial_write(&ch, 1);
    return 1;
}

size_t Print::write(const char *s) {
    if (s == nullptr) {
        return 0;
    }
    size_t n = strlen(s);
    sitl::serial_write(s, n);
    return n;
}

size_t Print::write(const uint8_t *buffer, size_t size) {
    sitl::serial_write((const char *)buffer, size);
    return size;
}

size_t Print::printNumber(unsigned long long n, int base, bool negative) {
    if (!rt.capture) {
        return 0;
    }
    if (base < 2) {
        base = 10;
    }
    char buf[8 * sizeof(unsigned long long) + 2];
    char *p = &buf[sizeof(buf) - 1];
    *p = '\0';
    do {
        unsigned digit = (unsigned)(n % (unsigned)base);
        *--p = (char)(digit < 10 ? '0' + digit : 'A' + digit - 10);
        n /= (unsigned)base;
    } while (n != 0);
    if (negative) {
        *--p = '-';
    }
    return write(p);
}

size_t Print::print(const char *s) { return write(s); }
size_t Print::print(char c) { return write((uint8_t)c); }
size_t Print::print(unsigned char n, int base) { return printNumber(n, base, false); }
size_t Print::print(unsigned int n, int base) { return printNumber(n, base, false); }
size_t Print::print(unsigned long n, int base) { return printNumber(n, base, false); }
size_t Print::print(unsigned long long n, int base) { return printNumber(n, base, false); }
size_t Print::print(int n, int base) { return print((long long)n, base); }
size_t Print::print(long n, int base) { return print((long long)n, base); }

size_t Print::print(long long n, int base) {
    if (base == 10 && n < 0) {
        return printNumber(0ULL - (unsigned long long)n, 10, true);
    }
    /* Other bases print the two's complement, as the core does. */
    return printNumber((unsigned long)n, base, false);
}

size_t Print::print(double n, int digits) {
    if (!rt.capture) {
        return 0;
    }
    /* The core's printFloat: nan, inf, ovf for what it cannot print, else fixed point. */
    if (std::isnan(n)) {
        return write("nan");
    }
    if (std::isinf(n)) {
        return write("inf");
    }
    if (n > 4294967040.0 || n < -4294967040.0) {
        return write("ovf");
    }
    char buf[64];
    if (digits < 0) {
        digits = 0;
    }
    snprintf(buf, sizeof(buf), "%.*f", digits > 20 ? 20 : digits, n);
    return write(buf);
}

size_t Print::println(void) { return write("\r\n"); }
size_t Print::println(const char *s) { return print(s) + println(); }
size_t Print::println(char c) { return print(c) + println(); }
size_t Print::println(unsigned char n, int base) { return print(n, base) + println(); }
size_t Print::println(int n, int base) { return print(n, base) + println(); }
size_t Print::println(unsigned int n, int base) { return print(n, base) + println(); }
size_t Print::println(long n, int base) { return print(n, base) + println(); }
size_t Print::println(unsigned long n, int base) { return print(n, base) + println(); }
size_t Print::println(long long n, int base) { return print(n, base) + println(); }
size_t Print::println(unsigned long long n, int base) { return print(n, base) + println(); }
size_t Print::println(double n, int digits) { return print(n, digits) + println(); }

size_t Print::printf(const char *format, ...) {
    if (!rt.capture) {
        return 0;
    }
    char buf[256];
    va_list args;
    va_start(args, format);
    int n = vsnprintf(buf, sizeof(buf), format, args);
    va_end(args);
    if (n < 0) {
        return 0;
    }
    size_t len = (size_t)n < sizeof(buf) ? (size_t)n : sizeof(buf) - 1;
    sitl::serial_write(buf, len);
    return len;
}

void HardwareSerial::begin(unsigned long) {}
void HardwareSerial::end(void) {}
int HardwareSerial::available(void) { return 0; }
int HardwareSerial::read(void) { return -1; }
void HardwareSerial::flush(void) {}

// ---------------------------------------------------------------- wire

void TwoWire::begin(void) { rt.wire_begun = true; }

void TwoWire::begin(uint8_t address) {
    rt.wire_begun = true;
    rt.wire_address = address;
}

void TwoWire::begin(int address) { begin((uint8_t)address); }

void TwoWire::onReceive(void (*handler)(int)) { rt.on_receive = handler; }

void TwoWire::onRequest(void (*handler)(void)) { rt.on_request = handler; }

int TwoWire::available(void) { return rt.rx_len - rt.rx_pos; }

int TwoWire::read(void) {
    if (rt.rx_pos >= rt.rx_len) {
        return -1;
    }
    return rt.rx[rt.rx_pos++];
}

int TwoWire::peek(void) { return rt.rx_pos < rt.rx_len ? rt.rx[rt.rx_pos] : -1; }

size_t TwoWire::write(uint8_t data) {
    if (rt.tx_len >= sitl::WIRE_BYTES) {
        return 0;
    }
    rt.tx[rt.tx_len++] = data;
    return 1;
}

size_t TwoWire::write(const uint8_t *data, size_t quantity) {
    size_t n = 0;
    while (n < quantity && write(data[n])) {
        n++;
    }
    return n;
}

void TwoWire::setClock(uint32_t) {}
