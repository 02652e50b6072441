/* usmswitch firmware: CRC, COBS and message sizes (docs/mcu-protocol.md sections 1 and 5). */
#include "proto.h"

#ifdef __AVR__
#include <util/crc16.h>
#endif

uint16_t crc16_update(uint16_t crc, uint8_t byte)
{
#ifdef __AVR__
    /* avr-libc's hand-written step (no table): the CCITT polynomial MSB-first, as below */
    return _crc_xmodem_update(crc, byte);
#else
    /* Bitwise MSB-first, the reference for the native tests. */
    crc ^= (uint16_t)byte << 8;
    for (uint8_t i = 0; i < 8; i++)
        crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    return crc;
#endif
}

uint16_t crc16(const uint8_t *data, uint8_t len)
{
    uint16_t crc = 0xFFFFu;
    while (len--)
        crc = crc16_update(crc, *data++);
    return crc;
}

uint8_t cobs_encode(const uint8_t *in, uint8_t len, uint8_t *out)
{
    uint8_t code_at = 0, o = 1, code = 1;
    for (uint8_t i = 0; i < len; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
            continue;
        }
        out[o++] = in[i];
        if (++code == 0xFF) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        }
    }
    out[code_at] = code;
    return o;
}

int16_t cobs_decode(const uint8_t *in, uint8_t len, uint8_t *out)
{
    uint8_t i = 0;
    int16_t o = 0;
    while (i < len) {
        uint8_t code = in[i];
        if (code == 0 || (uint16_t)i + code > len)
            return -1;
        for (uint8_t k = 1; k < code; k++) {
            uint8_t b = in[i + k];
            if (b == 0)
                return -1;
            out[o++] = b;
        }
        i = (uint8_t)(i + code);
        if (code != 0xFF && i < len)
            out[o++] = 0;
    }
    return o;
}

uint8_t msg_body_size_ok(uint8_t type, uint8_t len)
{
    int8_t size = msg_body_size(type);
    if (size < 0 || size == (int8_t)len)
        return 1; /* an unknown type (a newer minor version's) is answered whatever its size */
    /* the 1.0/1.1 bodies of what 1.2 extended */
    return (type == MT_PONG && len == 13) || (type == MT_EDGE && len == 6);
}

int8_t msg_body_size(uint8_t type)
{
    switch (type) {
    case MT_HELLO: return 4;
    case MT_ARM: return 11;
    case MT_COMMAND: return 7;
    case MT_STOP: return 1;
    case MT_PING: return 4;
    case MT_HELLO_ACK: return 17; /* a 1.0 session's: 16 */
    case MT_ACK: return 10;
    case MT_PONG: return 17; /* a 1.0/1.1 session's: 13 */
    case MT_EDGE: return 7;  /* a 1.0/1.1 session's: 6 */
    case MT_START: return 11;
    case MT_STOPPED: return 7;
    case MT_STROKE: return 20;
    case MT_FAULT: return 7;
    case MT_BOOT: return 3;
    default: return -1;
    }
}
