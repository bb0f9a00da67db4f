/*
 * The uStepper S32 library's calls, for the host build of the joint firmware
 * (bioscara_gym SITL). Written for this project from what the library's
 * public source (github.com/uStepper/uStepperS32: UstepperS32.cpp,
 * peripherals/TMC5130 (.h/.cpp), peripherals/TLE5012B.cpp, the callbacks,
 * utils/velocityEstimator.cpp) does; no code of it is copied. The chip
 * parts are models: the TMC5130's ramp generator (positioning and velocity
 * modes at its AMAX/DMAX/VMAX) and the TLE5012B encoder, whose angle is the
 * host motor model's.
 */
#include <UstepperS32.h>

#include "sitl.h"

using sitl::rt;

namespace {

/* The driver's clock: the library converts units for 10 MHz. */
const double DRIVER_CLOCK_HZ = DRIVERCLOCKFREQ;
/* Microsteps/s per VMAX unit: fCLK / 2^24 (TMC5130 datasheet). */
const double VELOCITY_UNIT = DRIVER_CLOCK_HZ / 16777216.0;
/* Microsteps/s^2 per AMAX unit: fCLK^2 / (512 * 256) / 2^24. */
const double ACCELERATION_UNIT = DRIVER_CLOCK_HZ * DRIVER_CLOCK_HZ / 2199023255552.0;
/* VMAX and AMAX/DMAX limits the library saturates at. */
const uint32_t VMAX_LIMIT = 0x7FFE00;
const uint16_t AMAX_LIMIT = 0xFFFE;
/* VSTOP in positioning mode (the library writes at least 10). */
const double VSTOP_UNITS = 10.0;
/* Sub-steps of the ramp generator per host step. */
const int RAMP_SUBSTEPS = 20;
/* The library's 1 kHz timer period as it computes it (float). */
const float TIMER_PERIOD_S = 1.0f / 1000.0f;
/* The velocity estimator's gains (utils/velocityEstimator.h). */
const float ESTIMATOR_KP = 120.0f;
const float ESTIMATOR_KI = 1900.0f;

double approach(double value, double target, double step) {
    if (value < target) {
        return value + step < target ? value + step : target;
    }
    return value - step > target ? value - step : target;
}

/* A float to uint16_t conversion on the chip: VCVT to 32 bits, then the low 16 bits. */
uint16_t to_u16(float value) { return (uint16_t)(sitl::to_u32(value) & 0xFFFF); }

}  // namespace

// ---------------------------------------------------------------- TLE5012B

void TLE5012B::readSensor(void) {
    sensor = (uint16_t)(sitl::sensor_counts() & 0x7FFF);
}

void TLE5012B::sitlInit(void) {
    readSensor();
    encoderOffset = sensor;
    angle = 0;
    angleMoved = 0;
    sitlSample();
}

void TLE5012B::sitlSample(void) {
    readSensor();
    uint16_t now = (uint16_t)((sensor - encoderOffset) & 0x7FFF);
    /* The sensor counts 15 bits a turn; a change of more than half a turn
     * between two samples is read as the shorter way round. */
    int32_t delta = (int32_t)now - (int32_t)angle;
    if (delta < -0x4000) {
        delta += 0x8000;
    } else if (delta > 0x4000) {
        delta -= 0x8000;
    }
    angleMoved += delta;
    angle = now;
    /* The velocity estimator, one iteration per sample. */
    posEst += velEst * TIMER_PERIOD_S;
    posError = (float)angleMoved - posEst;
    velIntegrator += posError * ESTIMATOR_KI * TIMER_PERIOD_S;
    velEst = posError * ESTIMATOR_KP + velIntegrator;
}

void TLE5012B::sitlShift(int32_t counts) {
    angleMoved += counts;
    posEst += (float)counts;
}

void TLE5012B::setHome(float initialAngle) {
    readSensor();
    encoderOffset = sensor;
    angle = 0;
    angleMoved = (int32_t)to_u16((float)(initialAngle * (32768.0 / 360.0)));
    posError = posEst = velIntegrator = velEst = 0.0f;
}

float TLE5012B::getAngle(void) {
    sitl::spin();
    return (float)((360.0 / 32768.0) * (float)angle);
}

uint16_t TLE5012B::getAngleRaw(void) {
    sitl::spin();
    return angle;
}

float TLE5012B::getAngleMoved(bool) {
    sitl::spin();
    return (float)((360.0 / 32768.0) * (float)angleMoved);
}

int32_t TLE5012B::getAngleMovedRaw(bool) {
    sitl::spin();
    return angleMoved;
}

float TLE5012B::getSpeed(uint32_t stepSize) {
    sitl::spin();
    return (float)(((float)stepSize * 200.0) * (1.0 / 32768.0) * velIntegrator);
}

float TLE5012B::getRPM(void) {
    sitl::spin();
    return (float)(velIntegrator * 60.0 * (1.0 / 32768.0));
}

// ----------------------------------------------------------------- TMC5130

void TMC5130::sitlReset(void) {
    /* driver.init(): registers cleared, currents, positioning mode at the
     * default profile, position 0, AMAX/DMAX 0xFFFE, stopped. */
    VMAX_ = 200000;
    AMAX_ = 100;
    DMAX_ = 600;
    mode = DRIVER_STOP;
    shaft = 0;
    x = 0.0;
    v = 0.0;
    xTarget = xActual = 0;
    regXtarget = 0;
    updateCurrent();
    setRampMode(POSITIONING_MODE);
    setDeceleration(AMAX_LIMIT);
    setAcceleration(AMAX_LIMIT);
    stop();
}

void TMC5130::setRampMode(uint8_t rampMode) {
    regAmax = AMAX_;
    regVmax = VMAX_;
    if (rampMode == POSITIONING_MODE) {
        regDmax = DMAX_;
        regRampmode = POSITIONING_MODE;
    } else {
        regDmax = 0;
        regRampmode = VELOCITY_MODE_POS;
    }
}

void TMC5130::setDirection(bool direction) {
    mode = DRIVER_VELOCITY;
    regRampmode = direction ? VELOCITY_MODE_POS : VELOCITY_MODE_NEG;
}

void TMC5130::setPosition(int32_t position) {
    mode = DRIVER_POSITION;
    setRampMode(POSITIONING_MODE);
    regXtarget = position;
    xTarget = position;
}

void TMC5130::setVelocity(uint32_t velocity) {
    VMAX_ = velocity > VMAX_LIMIT ? VMAX_LIMIT : velocity;
    regVmax = VMAX_;
}

void TMC5130::setAcceleration(uint32_t acceleration) {
    /* The library keeps AMAX in 16 bits: the value is cut to its low 16 bits
     * first, and only 0xFFFF is then brought down to 0xFFFE. */
    AMAX_ = (uint16_t)acceleration;
    if (AMAX_ > AMAX_LIMIT) {
        AMAX_ = AMAX_LIMIT;
    }
    regAmax = AMAX_;
}

void TMC5130::setDeceleration(uint32_t deceleration) {
    DMAX_ = (uint16_t)deceleration;
    if (DMAX_ > AMAX_LIMIT) {
        DMAX_ = AMAX_LIMIT;
    }
    regDmax = DMAX_;
}

void TMC5130::setCurrent(uint8_t value) {
    current = value;
    updateCurrent();
}

void TMC5130::setHoldCurrent(uint8_t value) {
    holdCurrent = value;
    updateCurrent();
}

void TMC5130::updateCurrent(void) {
    /* IHOLD_IRUN holds 5 bits of each. */
    regIrun = current & 0x1F;
    regIhold = holdCurrent & 0x1F;
}

void TMC5130::setShaftDirection(bool direction) {
    shaft = direction ? 1 : 0;
}

void TMC5130::stop(void) {
    mode = DRIVER_STOP;
    setVelocity(0);
}

int32_t TMC5130::getVelocity(void) {
    sitl::spin();
    return (int32_t)(v / VELOCITY_UNIT);
}

int32_t TMC5130::getPosition(void) {
    sitl::spin();
    return (int32_t)floor(x + 1e-9);
}

void TMC5130::setHome(int32_t initialSteps) {
    if (mode == DRIVER_POSITION) {
        int32_t target = (int32_t)((uint32_t)regXtarget - (uint32_t)getPosition());
        xTarget = (int32_t)((uint32_t)target + (uint32_t)initialSteps);
        xActual = initialSteps;
        x = initialSteps;
        regXtarget = xTarget;
    } else {
        xTarget = xActual = initialSteps;
        x = initialSteps;
        regXtarget = initialSteps;
    }
}

int32_t TMC5130::writeRegister(uint8_t address, uint32_t datagram) {
    switch (address) {
        case XACTUAL:
            /* A new position counter; the coils' microstep position stays. */
            x = (int32_t)datagram;
            break;
        case XTARGET:
            regXtarget = (int32_t)datagram;
            break;
        case RAMPMODE:
            regRampmode = (uint8_t)(datagram & 3);
            break;
        case VMAX_REG:
            regVmax = datagram & 0x7FFFFF;
            break;
        case AMAX_REG:
            regAmax = (uint16_t)datagram;
            break;
        case DMAX_REG:
            regDmax = (uint16_t)datagram;
            break;
        default:
            break;
    }
    return sitlStatus();
}

int32_t TMC5130::readRegister(uint8_t address) {
    sitl::spin();
    switch (address) {
        case XACTUAL:
            return getPosition();
        case VACTUAL:
            return (int32_t)((uint32_t)getVelocity() & 0xFFFFFF);
        case XTARGET:
            return regXtarget;
        case RAMPMODE:
            return regRampmode;
        case RAMP_STAT:
            return (sitlStatus() & POSITION_REACHED) ? (1 << 9) : 0;
        default:
            return 0;
    }
}

uint16_t TMC5130::getStallValue(void) {
    sitl::spin();
    return 0;
}

void TMC5130::setRPM(float rpm) {
    float rpmToVelocity = (float)(279620.267 * 200 * 256) / DRIVER_CLOCK_HZ;
    int32_t velocityDir = sitl::to_i32(rpmToVelocity * rpm);
    setDirection(velocityDir > 0);
    uint32_t velocity = velocityDir < 0 ? 0u - (uint32_t)velocityDir : (uint32_t)velocityDir;
    setVelocity(velocity);
}

uint8_t TMC5130::sitlStatus(void) {
    uint8_t status = 0;
    if (getPosition() == regXtarget) {
        status |= POSITION_REACHED;
    }
    double target = regVmax * VELOCITY_UNIT;
    if (regRampmode == VELOCITY_MODE_NEG) {
        target = -target;
    }
    if (regRampmode != POSITIONING_MODE && v == target) {
        status |= VELOCITY_REACHED;
    }
    if (v == 0.0) {
        status |= STANDSTILL;
    }
    return status;
}

double TMC5130::sitlTorque(bool moving) {
    /* Run current while the ramp moves, hold current at standstill, as a
     * fraction of the 5-bit scale (the chip's standstill delay is not modelled). */
    return (moving || v != 0.0 ? regIrun : regIhold) / 31.0;
}

void TMC5130::sitlShift(int32_t microsteps) { x += microsteps; }

double TMC5130::sitlRamp(double dt) {
    /* The ramp generator over dt seconds; returns how far it moved the coils'
     * microstep position (writes to XACTUAL do not move it). */
    const double h = dt / RAMP_SUBSTEPS;
    const double amax = regAmax * ACCELERATION_UNIT;
    const double vmax = regVmax * VELOCITY_UNIT;
    const double start = x;
    for (int i = 0; i < RAMP_SUBSTEPS; i++) {
        double v0 = v;
        if (regRampmode == VELOCITY_MODE_POS || regRampmode == VELOCITY_MODE_NEG) {
            double target = regRampmode == VELOCITY_MODE_POS ? vmax : -vmax;
            v = approach(v, target, amax * h);
            x += 0.5 * (v0 + v) * h;
        } else if (regRampmode == POSITIONING_MODE) {
            double d = regXtarget - x;
            if (d == 0.0 && v == 0.0) {
                continue;
            }
            const double dmax = regDmax * ACCELERATION_UNIT;
            double brake = sqrt(2.0 * dmax * fabs(d));
            double wanted = d >= 0.0 ? (vmax < brake ? vmax : brake) : -(vmax < brake ? vmax : brake);
            bool speeding_up = v * wanted >= 0.0 && fabs(wanted) > fabs(v);
            v = approach(v, wanted, (speeding_up ? amax : dmax) * h);
            x += 0.5 * (v0 + v) * h;
            double left = regXtarget - x;
            bool crossed = (left > 0.0) != (d > 0.0) || left == 0.0;
            double slow = 2.0 * dmax * h + VSTOP_UNITS * VELOCITY_UNIT;
            if ((crossed || fabs(left) < 0.5) && fabs(v) <= slow) {
                x = regXtarget;
                v = 0.0;
            }
        } else {
            v = approach(v, 0.0, amax * h);
            x += 0.5 * (v0 + v) * h;
        }
    }
    double moved = x - start;
    return shaft ? -moved : moved;
}

// ------------------------------------------------------------- UstepperS32

UstepperS32::UstepperS32() {
    rt.stepper = this;
    microSteps = 256;
    setMaxAcceleration(2000.0f, false);
    setMaxDeceleration(2000.0f, false);
    setMaxVelocity(100.0f, false);
}

UstepperS32::UstepperS32(float acceleration, float velocity) {
    rt.stepper = this;
    microSteps = 256;
    setMaxDeceleration(acceleration, false);
    setMaxAcceleration(acceleration, false);
    setMaxVelocity(velocity, false);
}

void UstepperS32::setup(uint8_t setupMode, uint16_t fullstepsPerRevolution, float, float, float, uint16_t,
                        bool setHome, uint8_t, uint8_t, uint8_t) {
    encoder.sitlInit();
    driver.sitlReset();
    pidDisabled = true;
    fullSteps = fullstepsPerRevolution;
    angleToStep = (float)fullSteps * (float)microSteps / 360.0;
    rpmToVelocity = (float)(279620.267 * fullSteps * microSteps) / DRIVERCLOCKFREQ;
    double stepTime = 16777216.0 / DRIVERCLOCKFREQ;
    velToRpm = (float)(1.0 / ((fullSteps * microSteps) / (60.0 / stepTime)));
    driver.setDeceleration(sitl::to_u32(maxDeceleration));
    driver.setAcceleration(sitl::to_u32(maxAcceleration));
    setCurrent(40.0);
    setHoldCurrent(40.0);
    if (setHome) {
        encoder.setHome();
    }
    if (setupMode == DROPIN) {
        sitl::fault("stepper.setup(DROPIN): the drop-in mode (step/direction input) is not modelled");
    }
    mode = setupMode;
    rt.timer_on = true;
}

void UstepperS32::setRPM(float rpm) {
    int32_t velocityDir = sitl::to_i32(rpmToVelocity * rpm);
    driver.setDirection(velocityDir > 0);
    /* abs() of the int32: its most negative value stays itself, 0x80000000 unsigned. */
    uint32_t velocity = velocityDir < 0 ? 0u - (uint32_t)velocityDir : (uint32_t)velocityDir;
    driver.setVelocity(velocity);
}

float UstepperS32::getDriverRPM(void) { return (float)driver.getVelocity() * velToRpm; }

void UstepperS32::moveSteps(int32_t microsteps) {
    /* The profile is re-applied with 16-bit casts of AMAX and DMAX. */
    driver.setDeceleration(to_u16(maxDeceleration));
    driver.setAcceleration(to_u16(maxAcceleration));
    driver.setVelocity(sitl::to_u32(maxVelocity));
    int32_t current = driver.getPosition();
    driver.setPosition((int32_t)((uint32_t)current + (uint32_t)microsteps));
}

void UstepperS32::moveAngle(float angle) {
    float scaled = angle * angleToStep;
    moveSteps(angle < 0.0f ? sitl::to_i32(scaled - 0.5) : sitl::to_i32(scaled + 0.5));
}

void UstepperS32::moveToAngle(float angle) {
    float diff = angle - angleMoved();
    int32_t steps = sitl::to_i32((double)(fabsf(diff) * angleToStep) + 0.5);
    moveSteps(diff < 0.0f ? -steps : steps);
}

bool UstepperS32::getMotorState(uint8_t statusType) {
    sitl::spin();
    return (driver.sitlStatus() & statusType) ? 0 : 1;
}

void UstepperS32::runContinous(bool dir) {
    driver.setDeceleration(sitl::to_u32(maxDeceleration));
    driver.setAcceleration(sitl::to_u32(maxAcceleration));
    driver.setVelocity(sitl::to_u32(maxVelocity));
    driver.setRampMode(VELOCITY_MODE_POS);
    driver.setDirection(dir);
}

float UstepperS32::angleMoved(void) { return encoder.getAngleMoved(); }

void UstepperS32::setCurrent(double value) {
    driver.current = (value <= 100.0 && value >= 0.0) ? (uint8_t)ceil(0.31 * value) : 16;
    driver.updateCurrent();
}

void UstepperS32::setHoldCurrent(double value) {
    driver.holdCurrent = (value <= 100.0 && value >= 0.0) ? (uint8_t)ceil(0.31 * value) : 16;
    driver.updateCurrent();
}

void UstepperS32::setMaxAcceleration(float acceleration, bool applyToDriver) {
    acceleration *= (float)microSteps;
    maxAcceleration = (float)(fabsf(acceleration) * ACCELERATIONCONVERSION);
    if (applyToDriver) {
        driver.setAcceleration(sitl::to_u32(maxAcceleration));
    }
}

void UstepperS32::setMaxDeceleration(float deceleration, bool applyToDriver) {
    deceleration *= (float)microSteps;
    maxDeceleration = (float)(fabsf(deceleration) * ACCELERATIONCONVERSION);
    if (applyToDriver) {
        driver.setDeceleration(sitl::to_u32(maxDeceleration));
    }
}

void UstepperS32::setMaxVelocity(float velocity, bool applyToDriver) {
    velocity *= (float)microSteps;
    maxVelocity = (float)(fabsf(velocity) * VELOCITYCONVERSION);
    if (applyToDriver) {
        driver.setVelocity(sitl::to_u32(maxVelocity));
    }
}

void UstepperS32::setBrakeMode(uint8_t brakeMode, float brakeCurrent) {
    /* Freewheel and cool brake hold with no current; hard brake with brakeCurrent. */
    if (brakeMode == FREEWHEELBRAKE || brakeMode == COOLBRAKE) {
        setHoldCurrent(0.0);
    } else {
        setHoldCurrent(brakeCurrent);
    }
}

void UstepperS32::enablePid(void) {
    pidDisabled = false;
    mode = CLOSEDLOOP;
}

void UstepperS32::disablePid(void) {
    pidDisabled = true;
    mode = NORMAL;
}

void UstepperS32::enableClosedLoop(void) { enablePid(); }

void UstepperS32::disableClosedLoop(void) { disablePid(); }

void UstepperS32::setControlThreshold(float threshold) { controlThreshold = threshold; }

void UstepperS32::stop(bool stopMode) {
    if (stopMode == HARD) {
        driver.setDeceleration(AMAX_LIMIT);
        driver.setAcceleration(AMAX_LIMIT);
        setRPM(0);
        while (driver.getVelocity() != 0 && sitl::rt.fault[0] == '\0') {
            sitl::wait_ms(1);
        }
        driver.setDeceleration(sitl::to_u32(maxDeceleration));
        driver.setAcceleration(sitl::to_u32(maxAcceleration));
    } else {
        setRPM(0);
        while (driver.getVelocity() != 0 && sitl::rt.fault[0] == '\0') {
            sitl::wait_ms(1);
        }
    }
    driver.setPosition(driver.getPosition());
}

float UstepperS32::getPidError(void) {
    sitl::spin();
    return currentPidError;
}

void UstepperS32::checkOrientation(float distance) {
    bool pidEnabled = mode != NORMAL;
    if (pidEnabled) {
        disablePid();
    }
    driver.setShaftDirection(false);
    int inverted = 0;
    int noninverted = 0;
    /* Out and back until two runs agree on the direction the encoder turns. */
    while (inverted < 2 && noninverted < 2 && sitl::rt.fault[0] == '\0') {
        float startAngle = encoder.getAngleMoved();
        moveAngle(distance);
        while (getMotorState(POSITION_REACHED) && sitl::rt.fault[0] == '\0') {
            sitl::wait_ms(1);
        }
        if (encoder.getAngleMoved() < startAngle) {
            inverted++;
        } else {
            noninverted++;
        }
        moveAngle(-distance);
        while (getMotorState(POSITION_REACHED) && sitl::rt.fault[0] == '\0') {
            sitl::wait_ms(1);
        }
        if (inverted > 0 && noninverted > 0) {
            inverted = noninverted = 0;
        }
    }
    if (inverted > 0) {
        driver.setShaftDirection(true);
    }
    if (pidEnabled) {
        enablePid();
    }
}

void UstepperS32::sitlTimer(void) {
    /* The 1 kHz timer: sample the encoder; in closed-loop mode compare the
     * driver's position with the encoder's (both in microsteps) and, when
     * they differ by the control threshold or more, move the driver's
     * position counter onto the encoder and restore its target. */
    encoder.sitlSample();
    if (mode != CLOSEDLOOP || pidDisabled) {
        return;
    }
    int32_t stepsMoved = driver.getPosition();
    int32_t stepsMeasured = sitl::to_i32((microSteps * 200.0) * (1.0 / 32768.0) * encoder.getAngleMovedRaw());
    currentPidError = (float)(int32_t)((uint32_t)stepsMoved - (uint32_t)stepsMeasured);
    if (fabsf(currentPidError) >= controlThreshold) {
        driver.writeRegister(XACTUAL, (uint32_t)stepsMeasured);
        driver.writeRegister(XTARGET, (uint32_t)driver.xTarget);
    }
}

void UstepperS32::sitlState(SitlState &out) {
    out.xactual = driver.getPosition();
    out.xtarget = driver.regXtarget;
    out.vactual = driver.getVelocity();
    out.vmax = driver.regVmax;
    out.amax = driver.regAmax;
    out.dmax = driver.regDmax;
    out.rampmode = driver.regRampmode;
    out.irun = driver.regIrun;
    out.ihold = driver.regIhold;
    out.mode = mode;
    out.pid_error = currentPidError;
    out.angle_moved = encoder.getAngleMovedRaw();
    out.rpm = encoder.getRPM();
}
