/*
 * Internal interface of the SITL runtime (bioscara_gym): virtual time, the
 * firmware's coroutine, the I2C follower's buffers, the sensor input and the
 * captured serial output. Everything the runtime keeps is plain static data
 * of the shared library, so that the library's writable memory is the whole
 * state of one joint (saved and restored as an image, runtime.cpp).
 */
#ifndef BIOSCARA_SITL_INTERNAL_H
#define BIOSCARA_SITL_INTERNAL_H

#include <stddef.h>
#include <stdint.h>
#include <ucontext.h>

class UstepperS32;

namespace sitl {

/* Bytes of the firmware's own stack (the coroutine's). */
const size_t STACK_BYTES = 64 * 1024;
/* Captured serial output kept between two reads by the host. */
const size_t SERIAL_BYTES = 64 * 1024;
/* I2C buffer of the Arduino core's Wire library. */
const int WIRE_BYTES = 32;
/* Calls into the core or the library without yielding after which the
 * firmware is taken to be busy-waiting: one millisecond passes. */
const uint32_t SPIN_CALLS = 100000;

struct Runtime {
    int64_t now_us;        /* device time of the last 1 ms step */
    int64_t isr_us;        /* time of the running I2C transaction */
    uint32_t wake_ms;      /* the firmware resumes at this millis() */
    uint32_t waiting_ms;   /* length of the wait it is in */
    uint32_t spin;         /* core/library calls since the firmware last yielded */
    bool started;          /* the coroutine exists */
    bool booted;           /* setup() has returned */
    bool in_firmware;      /* running on the firmware's own stack */
    bool in_isr;           /* running an I2C event handler */
    bool timer_on;         /* the library's 1 kHz timer runs (after setup()) */
    uint64_t loops;        /* loop() passes begun */
    int64_t loop_us;       /* time the latest loop() pass began */
    ucontext_t host;       /* where the firmware yields to */
    ucontext_t firmware;   /* where the host resumes the firmware */
    /* I2C follower */
    bool wire_begun;
    uint8_t wire_address;
    void (*on_receive)(int);
    void (*on_request)(void);
    uint8_t rx[WIRE_BYTES];
    int rx_len;
    int rx_pos;
    uint8_t tx[WIRE_BYTES];
    int tx_len;
    /* the motor's encoder angle at the last step, and the sensor's zero */
    double encoder_deg;
    int64_t sensor_ref;
    /* serial output */
    bool capture;
    size_t serial_len;
    uint64_t serial_dropped;
    char serial[SERIAL_BYTES];
    /* the first fault the firmware made the stand-in see, empty if none */
    char fault[256];
    UstepperS32 *stepper;
};

extern Runtime rt;

/* Let ms milliseconds pass on the firmware's side (delay, the library's waits). */
void wait_ms(uint32_t ms);
/* Count one call from the firmware into the core or the library (busy-wait detection). */
void spin(void);
/* Record the first fault (printf-style); the host raises it after the call. */
void fault(const char *format, ...) __attribute__((format(printf, 1, 2)));
/* Append captured serial output. */
void serial_write(const char *data, size_t size);
/* The encoder's raw count of the motor's current angle (15-bit sensor, full resolution). */
int64_t sensor_counts(void);

/* Microsteps of the chip per motor turn: 200 full steps of 256. */
const double MICROSTEPS_PER_TURN = 51200.0;
/* Encoder counts per motor turn (TLE5012B, 15 bits). */
const double COUNTS_PER_TURN = 32768.0;

/* The Cortex-M4's float and double to integer conversions (VCVT): round
 * toward zero, saturate at the type's range, NaN gives 0. C++ leaves these
 * undefined out of range; the host's would differ from the chip's. */
uint32_t to_u32(double value);
int32_t to_i32(double value);

}  // namespace sitl

#endif
