/*
 * UstepperS32.h for the host build of the joint firmware (bioscara_gym SITL).
 *
 * The project's own stand-in for the uStepper S32 library's public
 * interface: the calls the joint firmware makes, each doing what the
 * library's public source (github.com/uStepper/uStepperS32) does, written
 * for this project (not a copy). The TMC5130 driver's ramp generator and
 * the TLE5012B encoder are modelled in ustepper.cpp; the motor behind them
 * is the host's motor model (runtime.cpp). Constants below are the
 * library's, with their meaning.
 */
#ifndef BIOSCARA_SITL_USTEPPERS32_H
#define BIOSCARA_SITL_USTEPPERS32_H

#include <Arduino.h>

/* setBrakeMode() modes. */
#define FREEWHEELBRAKE 0
#define COOLBRAKE 1
#define HARDBRAKE 2

/* runContinous() directions. */
#define CW 1
#define CCW 0

/* getMotorState() status bits (the TMC5130's SPI status byte). */
#define POSITION_REACHED 0x20
#define VELOCITY_REACHED 0x10
#define STANDSTILL 0x08
#define STALLGUARD2 0x04

/* stop() modes (a bool parameter: HARD is false). */
#define HARD 0
#define SOFT 1

/* setup() modes. */
#define NORMAL 0
#define DROPIN 1
#define CLOSEDLOOP 2
#define PID CLOSEDLOOP

/* The library's unit conversions for a 10 MHz driver clock. */
#define ACCELERATIONCONVERSION 0.0220
#define VELOCITYCONVERSION 1.677
#define DRIVERCLOCKFREQ 10000000.0

/* TMC5130 registers the stand-in models (readRegister/writeRegister). */
#define GCONF 0x00
#define RAMPMODE 0x20
#define XACTUAL 0x21
#define VACTUAL 0x22
#define AMAX_REG 0x26
#define VMAX_REG 0x27
#define DMAX_REG 0x28
#define XTARGET 0x2D
#define RAMP_STAT 0x35
#define DRV_STATUS 0x6F

/* TMC5130 RAMPMODE values. */
#define POSITIONING_MODE 0
#define VELOCITY_MODE_POS 1
#define VELOCITY_MODE_NEG 2
#define HOLD_MODE 3

/* The library's driver bookkeeping modes. */
#define DRIVER_STOP 0
#define DRIVER_POSITION 1
#define DRIVER_VELOCITY 2

class UstepperS32;

/* What the host may look at of the chip and the library (tests, docs). */
struct SitlState {
    int32_t xactual;
    int32_t xtarget;
    int32_t vactual;
    uint32_t vmax;
    uint16_t amax;
    uint16_t dmax;
    uint8_t rampmode;
    uint8_t irun;
    uint8_t ihold;
    uint8_t mode;
    float pid_error;
    int32_t angle_moved;
    float rpm;
};

/* The TLE5012B magnetic encoder, 15 bits a turn, sampled by the 1 kHz timer. */
class TLE5012B {
  public:
    void setHome(float initialAngle = 0);
    float getAngle(void);
    uint16_t getAngleRaw(void);
    float getAngleMoved(bool filtered = true);
    int32_t getAngleMovedRaw(bool filtered = true);
    float getSpeed(uint32_t stepSize = 256);
    float getRPM(void);

    /* Stand-in internals (the runtime's timer and teleport). */
    void sitlInit(void);
    void sitlSample(void);
    void sitlShift(int32_t counts);

  private:
    void readSensor(void);
    uint16_t angle = 0;
    uint16_t encoderOffset = 0;
    uint16_t sensor = 0;
    int32_t angleMoved = 0;
    /* The library's velocity estimator: a PI tracking loop on the counts. */
    float posError = 0.0f;
    float posEst = 0.0f;
    float velIntegrator = 0.0f;
    float velEst = 0.0f;
};

/* The TMC5130 driver and its ramp generator (positioning and velocity modes). */
class TMC5130 {
  public:
    void setPosition(int32_t position);
    void setVelocity(uint32_t velocity);
    void setAcceleration(uint32_t acceleration);
    void setDeceleration(uint32_t deceleration);
    void setCurrent(uint8_t current);
    void setHoldCurrent(uint8_t current);
    void setShaftDirection(bool direction);
    void stop(void);
    int32_t getVelocity(void);
    int32_t getPosition(void);
    void setHome(int32_t initialSteps = 0);
    int32_t writeRegister(uint8_t address, uint32_t datagram);
    int32_t readRegister(uint8_t address);
    uint16_t getStallValue(void);
    void setRPM(float rpm);

    /* target and actual position the library last set, microsteps */
    int32_t xTarget = 0;
    int32_t xActual = 0;

    /* Stand-in internals (the runtime's chip model). */
    void sitlReset(void);
    double sitlRamp(double dt);
    uint8_t sitlStatus(void);
    double sitlTorque(bool moving);
    void sitlShift(int32_t microsteps);

  private:
    friend class UstepperS32;
    void setRampMode(uint8_t mode);
    void setDirection(bool direction);
    void updateCurrent(void);
    /* the library's cached settings */
    uint32_t VMAX_ = 200000;
    uint16_t AMAX_ = 100;
    uint16_t DMAX_ = 600;
    uint8_t current = 16;
    uint8_t holdCurrent = 0;
    uint8_t mode = DRIVER_STOP;
    uint8_t shaft = 0;
    /* the chip's registers and ramp state */
    uint8_t regRampmode = POSITIONING_MODE;
    uint32_t regVmax = 0;
    uint16_t regAmax = 0;
    uint16_t regDmax = 0;
    int32_t regXtarget = 0;
    uint8_t regIrun = 0;
    uint8_t regIhold = 0;
    double x = 0.0; /* XACTUAL with its fraction, microsteps */
    double v = 0.0; /* VACTUAL, microsteps/s */
};

class UstepperS32 {
  public:
    TLE5012B encoder;
    TMC5130 driver;

    UstepperS32();
    UstepperS32(float acceleration, float velocity);
    void setup(uint8_t mode = NORMAL, uint16_t fullstepsPerRevolution = 200, float pTerm = 10,
               float iTerm = 0.2, float dTerm = 0.0, uint16_t dropinStepSize = 16, bool setHome = true,
               uint8_t invert = 0, uint8_t runCurrent = 50, uint8_t holdCurrent = 30);
    void setRPM(float rpm);
    float getDriverRPM(void);
    void moveSteps(int32_t microsteps);
    void moveAngle(float angle);
    void moveToAngle(float angle);
    bool getMotorState(uint8_t statusType = POSITION_REACHED);
    void runContinous(bool dir);
    float angleMoved(void);
    void setCurrent(double current);
    void setHoldCurrent(double current);
    void setMaxAcceleration(float acceleration, bool applyToDriver = true);
    void setMaxDeceleration(float deceleration, bool applyToDriver = true);
    void setMaxVelocity(float velocity, bool applyToDriver = true);
    void setBrakeMode(uint8_t mode, float brakeCurrent = 25.0);
    void enablePid(void);
    void disablePid(void);
    void enableClosedLoop(void);
    void disableClosedLoop(void);
    void setControlThreshold(float threshold);
    void stop(bool mode = HARD);
    float getPidError(void);
    void checkOrientation(float distance = 10);

    /* Stand-in internals: the 1 kHz timer interrupt, and a look at the state. */
    void sitlTimer(void);
    void sitlState(SitlState &out);

  private:
    float maxVelocity = 0.0f;
    float maxAcceleration = 0.0f;
    float maxDeceleration = 0.0f;
    float rpmToVelocity = 0.0f;
    float angleToStep = 0.0f;
    float velToRpm = 0.0f;
    uint16_t microSteps = 256;
    uint16_t fullSteps = 200;
    uint8_t mode = NORMAL;
    bool pidDisabled = true;
    float controlThreshold = 10.0f;
    float currentPidError = 0.0f;
};

#endif
