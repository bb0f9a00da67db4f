/*
 * The SITL runtime (bioscara_gym): virtual time, the firmware as a
 * coroutine, interrupts between its steps, and the C interface the host's
 * Python side calls through ctypes (hardware/sitl/device.py).
 *
 * Time advances in 1 ms steps, the period of the library's closed-loop
 * timer. A step is two calls: sitl_tick_begin runs the driver's ramp
 * generator over the millisecond and says how far it turned the coils and
 * at what current (the host's motor model moves meanwhile); sitl_tick_end
 * takes the motor's new encoder angle, runs the 1 kHz timer (encoder
 * sample, velocity estimator, closed loop) and then the firmware's own
 * code, if its delay() has run out, until it waits again. The firmware runs
 * on a stack of its own (ucontext), so a delay() deep inside a blocking
 * command returns to the host and resumes later. I2C events (sitl_transfer)
 * run on the host's stack between two steps, as the interrupts do between
 * the firmware's instructions on the chip.
 *
 * One loaded copy of the library is one joint: the firmware's globals and
 * everything here are the library's writable memory, which the host saves
 * and restores as an image (power-up state, snapshots).
 */
#include <Arduino.h>
#include <UstepperS32.h>
#include <link.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

#include "sitl.h"

#define SITL_API extern "C" __attribute__((visibility("default")))

namespace sitl {

Runtime rt;

alignas(64) static unsigned char firmware_stack[STACK_BYTES];

static void firmware_main(void) {
    setup();
    rt.booted = true;
    for (;;) {
        rt.loops++;
        rt.loop_us = rt.now_us;
        loop();
    }
}

static void resume_firmware(void) {
    rt.in_firmware = true;
    rt.spin = 0;
    swapcontext(&rt.host, &rt.firmware);
    rt.in_firmware = false;
}

static uint32_t now_ms(void) { return (uint32_t)(rt.now_us / 1000); }

void wait_ms(uint32_t ms) {
    if (!rt.in_firmware) {
        fault("a wait of %u ms outside the main loop (in an interrupt handler): the chip would not return",
              (unsigned)ms);
        return;
    }
    rt.wake_ms = now_ms() + ms;
    rt.waiting_ms = ms;
    swapcontext(&rt.firmware, &rt.host);
    rt.spin = 0;
}

void spin(void) {
    if (rt.in_firmware && ++rt.spin >= SPIN_CALLS) {
        wait_ms(1);
    }
}

void fault(const char *format, ...) {
    if (rt.fault[0] != '\0') {
        return;
    }
    va_list args;
    va_start(args, format);
    vsnprintf(rt.fault, sizeof(rt.fault), format, args);
    va_end(args);
    if (rt.fault[0] == '\0') {
        rt.fault[0] = '?';
    }
}

void serial_write(const char *data, size_t size) {
    if (!rt.capture) {
        return;
    }
    size_t room = SERIAL_BYTES - rt.serial_len;
    size_t n = size < room ? size : room;
    memcpy(rt.serial + rt.serial_len, data, n);
    rt.serial_len += n;
    rt.serial_dropped += size - n;
}

static int64_t counts_of(double deg) { return (int64_t)floor(deg * (COUNTS_PER_TURN / 360.0)); }

int64_t sensor_counts(void) { return counts_of(rt.encoder_deg) - rt.sensor_ref; }

uint32_t to_u32(double value) {
    if (!(value > 0.0)) {
        return 0;
    }
    if (value >= 4294967296.0) {
        return UINT32_MAX;
    }
    return (uint32_t)value;
}

int32_t to_i32(double value) {
    if (value != value) {
        return 0;
    }
    if (value >= 2147483648.0) {
        return INT32_MAX;
    }
    if (value <= -2147483649.0) {
        return INT32_MIN;
    }
    return (int32_t)value;
}

struct Range {
    uintptr_t start;
    uintptr_t end;
};

/* The writable part of this library's data segment (after RELRO). */
static int find_image(struct dl_phdr_info *info, size_t, void *data) {
    uintptr_t probe = (uintptr_t)&rt;
    const ElfW(Phdr) *writable = nullptr;
    uintptr_t relro_end = 0;
    uintptr_t page = (uintptr_t)sysconf(_SC_PAGESIZE);
    for (int i = 0; i < info->dlpi_phnum; i++) {
        const ElfW(Phdr) &p = info->dlpi_phdr[i];
        uintptr_t lo = info->dlpi_addr + p.p_vaddr;
        uintptr_t hi = lo + p.p_memsz;
        if (p.p_type == PT_LOAD && probe >= lo && probe < hi) {
            writable = &p;
        } else if (p.p_type == PT_GNU_RELRO) {
            relro_end = (lo + p.p_memsz) & ~(page - 1);
        }
    }
    if (writable == nullptr) {
        return 0;
    }
    Range *range = (Range *)data;
    range->start = info->dlpi_addr + writable->p_vaddr;
    range->end = range->start + writable->p_memsz;
    if (relro_end > range->start && relro_end < range->end) {
        range->start = relro_end;
    }
    return 1;
}

static Range image(void) {
    Range range = {0, 0};
    dl_iterate_phdr(find_image, &range);
    return range;
}

}  // namespace sitl

using sitl::rt;

/* Version of this interface; the Python side checks it. */
SITL_API int sitl_api_version(void) { return 1; }

/* Bytes of the library's writable memory: one joint's whole state. */
SITL_API size_t sitl_image_size(void) {
    sitl::Range range = sitl::image();
    return range.end - range.start;
}

SITL_API void sitl_image_save(void *buffer) {
    sitl::Range range = sitl::image();
    memcpy(buffer, (const void *)range.start, range.end - range.start);
}

SITL_API void sitl_image_load(const void *buffer) {
    sitl::Range range = sitl::image();
    memcpy((void *)range.start, buffer, range.end - range.start);
}

/* Power the joint up (from the library's image at load time) with the motor
 * at encoder_deg: the firmware's setup() starts. Returns -1 on a fault. */
SITL_API int sitl_power_on(double encoder_deg) {
    if (rt.started) {
        sitl::fault("power-on of a joint that is already running (restore the power-up image first)");
        return -1;
    }
    rt.now_us = 0;
    rt.encoder_deg = encoder_deg;
    rt.sensor_ref = sitl::counts_of(encoder_deg);
    getcontext(&rt.firmware);
    rt.firmware.uc_stack.ss_sp = sitl::firmware_stack;
    rt.firmware.uc_stack.ss_size = sizeof(sitl::firmware_stack);
    rt.firmware.uc_link = nullptr;
    makecontext(&rt.firmware, sitl::firmware_main, 0);
    rt.started = true;
    rt.wake_ms = 0;
    sitl::resume_firmware();
    return rt.fault[0] ? -1 : 0;
}

/* Whether setup() has returned (the joint answers on the bus). */
SITL_API int sitl_booted(void) { return rt.booted ? 1 : 0; }

/* Device time of the last step, microseconds since power-on. */
SITL_API int64_t sitl_now_us(void) { return rt.now_us; }

/* Run the driver's ramp over the next millisecond: returns how far it turned
 * the coils (motor degrees) and sets the current as a fraction of full scale. */
SITL_API double sitl_tick_begin(double *torque_fraction) {
    UstepperS32 *stepper = rt.stepper;
    if (stepper == nullptr) {
        *torque_fraction = 0.0;
        return 0.0;
    }
    double moved = stepper->driver.sitlRamp(0.001);
    *torque_fraction = stepper->driver.sitlTorque(moved != 0.0);
    return moved * (360.0 / sitl::MICROSTEPS_PER_TURN);
}

/* End the millisecond with the motor's encoder at encoder_deg: the 1 kHz
 * timer, then the firmware if its wait is over. Returns 1 on a fault. */
SITL_API int sitl_tick_end(double encoder_deg) {
    rt.now_us += 1000;
    rt.encoder_deg = encoder_deg;
    if (rt.timer_on && rt.stepper != nullptr) {
        rt.stepper->sitlTimer();
    }
    if (rt.started && rt.fault[0] == '\0' && (int32_t)(sitl::now_ms() - rt.wake_ms) >= 0) {
        sitl::resume_firmware();
    }
    return rt.fault[0] ? 1 : 0;
}

/* One I2C transaction at at_us (within the current millisecond): the write
 * phase runs the receive handler (len > 0), the read phase the request
 * handler (read_len > 0); the reply is what it wrote, padded with 0xFF.
 * Returns -1 on a fault. */
SITL_API int sitl_transfer(int64_t at_us, const uint8_t *data, int len, uint8_t *reply, int read_len) {
    if (at_us < rt.now_us || at_us >= rt.now_us + 1000) {
        sitl::fault("a transaction at %lld us outside the device's current millisecond (%lld us)",
                    (long long)at_us, (long long)rt.now_us);
        return -1;
    }
    rt.in_isr = true;
    rt.isr_us = at_us;
    if (len > 0) {
        int n = len < sitl::WIRE_BYTES ? len : sitl::WIRE_BYTES;
        memcpy(rt.rx, data, (size_t)n);
        rt.rx_len = n;
        rt.rx_pos = 0;
        if (rt.on_receive != nullptr) {
            rt.on_receive(n);
        }
    }
    if (read_len > 0) {
        rt.tx_len = 0;
        if (rt.on_request != nullptr) {
            rt.on_request();
        }
        for (int i = 0; i < read_len; i++) {
            reply[i] = i < rt.tx_len ? rt.tx[i] : 0xFF;
        }
    }
    rt.in_isr = false;
    return rt.fault[0] ? -1 : 0;
}

/* loop() passes begun since power-on; *began_us: when the latest began;
 * *wake_us and *wait_ms: when the firmware's current wait ends, and its length. */
SITL_API uint64_t sitl_loops(int64_t *began_us, int64_t *wake_us, uint32_t *wait_ms) {
    *began_us = rt.loop_us;
    *wake_us = (int64_t)rt.wake_ms * 1000;
    *wait_ms = rt.waiting_ms;
    return rt.loops;
}

/* The I2C address the firmware joined the bus with (Wire.begin), or -1. */
SITL_API int sitl_address(void) { return rt.wire_begun ? rt.wire_address : -1; }

/* Keep the firmware's serial output (on), or drop it (off, the default). */
SITL_API void sitl_capture_serial(int on) { rt.capture = on != 0; }

/* Move up to capacity bytes of captured serial output into buffer; returns how many. */
SITL_API size_t sitl_read_serial(char *buffer, size_t capacity) {
    size_t n = rt.serial_len < capacity ? rt.serial_len : capacity;
    memcpy(buffer, rt.serial, n);
    memmove(rt.serial, rt.serial + n, rt.serial_len - n);
    rt.serial_len -= n;
    return n;
}

/* Bytes of serial output dropped because the host did not read them in time. */
SITL_API uint64_t sitl_serial_dropped(void) { return rt.serial_dropped; }

/* The first fault, or an empty string. */
SITL_API const char *sitl_fault(void) { return rt.fault; }

/* The motor was moved by delta_deg outside physics (a simulation's teleport):
 * the encoder's count and the driver's position follow without a jump in the
 * velocity estimate or the closed loop's error. */
SITL_API void sitl_teleport(double delta_deg) {
    int64_t before = sitl::counts_of(rt.encoder_deg);
    int64_t after = sitl::counts_of(rt.encoder_deg + delta_deg);
    rt.encoder_deg += delta_deg;
    rt.sensor_ref += after - before;
    if (rt.stepper != nullptr) {
        rt.stepper->encoder.sitlShift((int32_t)(after - before));
        rt.stepper->driver.sitlShift((int32_t)llround(delta_deg * (sitl::MICROSTEPS_PER_TURN / 360.0)));
    }
}

/* The chip's and the library's state, for tests and documentation. */
SITL_API int sitl_state(SitlState *out) {
    if (rt.stepper == nullptr) {
        return -1;
    }
    rt.stepper->sitlState(*out);
    return 0;
}
