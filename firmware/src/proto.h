/* usmswitch firmware: wire protocol 1.2 constants and codec (docs/mcu-protocol.md).
 * Pure C99, no hardware: compiles for the AVR and natively for the host unit tests. */
#ifndef USMSWITCH_PROTO_H
#define USMSWITCH_PROTO_H

#include <stdint.h>

#define PROTO_MAJOR 1
#define PROTO_MINOR 2
#define FW_VERSION 0x0102u
#define MAX_DELAY_US 1000000UL
#define MAX_COMMAND_SKEW_US 1000000UL
#define MAX_PAYLOAD 64
#define MAX_ENCODED (MAX_PAYLOAD + 1)

enum msg_type {
    MT_HELLO = 0x01, MT_ARM = 0x02, MT_COMMAND = 0x03, MT_STOP = 0x04, MT_PING = 0x05,
    MT_HELLO_ACK = 0x81, MT_ACK = 0x82, MT_PONG = 0x83,
    MT_EDGE = 0x90, MT_START = 0x91, MT_STOPPED = 0x92, MT_STROKE = 0x93, MT_FAULT = 0x94,
    MT_BOOT = 0x95 /* 1.1 */
};

enum caps {
    CAP_HW_DELAY = 0x01, CAP_EDGE_STAMP = 0x02, CAP_STROKE_REPORT = 0x04,
    CAP_STOP_ON_ARRIVAL = 0x08, CAP_WATCHDOG = 0x10
};
#define ALL_CAPS 0x1FUL

enum status {
    ST_OK = 0, ST_NOT_SYNCED = 1, ST_NOT_ARMED = 2, ST_BUSY = 3, ST_BAD_ARG = 4,
    ST_BAD_TIME = 5, ST_UNKNOWN_TYPE = 6
};

enum stop_reason {
    SR_ARRIVED = 0, SR_HOST = 1, SR_STALL = 2, SR_WATCHDOG = 3, SR_RESET = 4, SR_FAULT = 5
};

/* HELLO_ACK.reset_cause (1.1) and BOOT: MCUSR's bits as the chip sets them; 0 = not known. */
enum reset_cause {
    RC_POWER_ON = 0x01, RC_EXTERNAL = 0x02, RC_BROWN_OUT = 0x04, RC_WATCHDOG = 0x08, RC_JTAG = 0x10
};

/* FC_SENSORS: at a start the source sensor was not active (detail: the sensors, bit 0 A, bit 1 B);
 * FC_DRIVE: the drive output was on with no stroke running (detail 1); FC_EVENTS_LOST (1.2): the
 * interrupt event queue was full and events were lost (detail: how many since the last report).
 * (5 is the host codec's LATE_START, never sent.) */
enum fault_code { FC_STALL = 1, FC_HOST_SILENT = 2, FC_SENSORS = 3, FC_DRIVE = 4, FC_EVENTS_LOST = 6 };

enum stroke_flags {
    SF_DEPARTED = 0x01, SF_ARRIVED = 0x02, SF_STALL = 0x04, SF_HOST_STOP = 0x08,
    SF_LATE = 0x10, SF_WATCHDOG = 0x20,
    SF_EVENTS_LOST = 0x40, /* 1.2: ended because interrupt events were lost */
    SF_MISSED_EDGE = 0x80  /* 1.2: a stamp of it is a missed edge's (EF_MISSED), not a capture's */
};


enum state_flags {
    STF_SYNCED = 0x01, STF_ARMED = 0x02, STF_DRIVE_ON = 0x04, STF_SENSOR_A = 0x08, STF_SENSOR_B = 0x10
};

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor. On the AVR the
 * update is avr-libc's _crc_xmodem_update (the same MSB-first 0x1021 step; XMODEM differs only
 * in its initial value, 0). */
uint16_t crc16_update(uint16_t crc, uint8_t byte);
uint16_t crc16(const uint8_t *data, uint8_t len);

/* COBS. encode writes at most len + len / 254 + 1 bytes (no delimiter) and returns the count.
 * decode returns the decoded length, or -1 on a zero byte or a code running past the end. */
uint8_t cobs_encode(const uint8_t *in, uint8_t len, uint8_t *out);
int16_t cobs_decode(const uint8_t *in, uint8_t len, uint8_t *out);

/* Body size of a message type (host or device direction; HELLO_ACK: this version's layout), -1
 * for a type this version lacks. */
int8_t msg_body_size(uint8_t type);
/* Whether a body of len bytes is one of type's layouts (any for a type this version lacks). */
uint8_t msg_body_size_ok(uint8_t type, uint8_t len);

/* Little-endian field access. */
static inline uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }
static inline uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static inline uint8_t *put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    return p + 2;
}
static inline uint8_t *put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
    return p + 4;
}

#endif
