/* usmswitch firmware: the protocol core (framing, sequence numbers, state machine).
 *
 * Hardware-free: it talks to the board only through the hal_* functions below, which the AVR
 * layer (avr/board.c) implements with timers 4/5 and USART0, and the native tests with a fake.
 * Single-threaded: every core_* call comes from the main loop, never from an interrupt; the
 * hardware layer hands interrupt-time facts (start fired, edge captured) over as events. */
#ifndef USMSWITCH_CORE_H
#define USMSWITCH_CORE_H

#include <stdint.h>

/* ---- implemented by the hardware layer ---- */
/* The 32-bit free-running microsecond clock (wraps every 2^32 us). */
uint32_t hal_now_us(void);
/* Queue bytes for the UART (blocks while the transmit ring is full). */
void hal_tx(const uint8_t *buf, uint8_t len);
/* Set the direction output, then switch the drive on at device instant due_us by hardware
 * compare, arming STOP_ON_ARRIVAL for sensor dest (0 A, 1 B). If due_us is already past (or too
 * close to arm a compare), the drive goes on at once. Either way the hardware layer later calls
 * core_start() with the instant the drive went on. */
void hal_drive_schedule(uint32_t due_us, uint8_t direction, uint8_t dest);
/* Drive off now; cancels a scheduled start and disarms the arrival stop. */
void hal_drive_off(void);
/* Whether the drive output is on now. */
uint8_t hal_drive_is_on(void);
/* Current sensor levels: bit 0 sensor A active, bit 1 sensor B active. */
uint8_t hal_sensors(void);

/* EDGE.flags (protocol 1.2): EF_MISSED the capture unit missed the edge (found by reading the pin
 * back); its stamp is when the firmware found it, after the edge. EF_CUT: an arrival known from
 * the external interrupt's drive cut, stamped by it. */
enum edge_flags { EF_MISSED = 0x01, EF_CUT = 0x02 };

/* ---- called by the hardware layer's main loop ---- */
void core_init(void);
/* Once after core_init, interrupts on: remember the reset cause (MCUSR's bits) for HELLO_ACK and
 * announce the start-up to whoever listens (BOOT). */
void core_boot(uint8_t reset_cause);
/* One received UART byte. */
void core_rx_byte(uint8_t b);
/* The drive went on at t_us (compare match, or at once for a late start). */
void core_start(uint32_t t_us);
/* A sensor edge at t_us: channel 0 A / 1 B, level 1 active, 0 released; flags EF_* (proto.h):
 * 0 for a capture's edge, EF_MISSED for one the capture unit missed (found by reading the pin
 * back, stamped then), EF_CUT too for an arrival known from the external interrupt's cut. */
void core_edge(uint8_t channel, uint8_t level, uint32_t t_us, uint8_t flags);
/* Whether an active edge on this channel would be the running stroke's arrival. */
uint8_t core_wants_arrival(uint8_t channel);
/* The board lost n interrupt events (its queue was full): reported (FAULT EVENTS_LOST, PONG's
 * counter), and a running stroke ends with it. */
void core_events_lost(uint16_t n, uint32_t now);
/* Timeouts: the watchdog and the stroke timeout. Call every main-loop pass. Returns how long
 * the main loop may sleep: the microseconds until the next timeout falls due, UINT32_MAX when
 * none is running. */
uint32_t core_poll(void);

/* Counters for tests and the PONG. */
struct core_stats {
    uint16_t rx_errors;  /* frames dropped since the last HELLO */
    uint16_t rx_lost;    /* host frames found missing by sequence since the last HELLO */
    uint16_t tx_seq;     /* next sequence number to send */
    uint8_t synced;
};
void core_get_stats(struct core_stats *out);

#endif
