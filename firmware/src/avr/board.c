/* usmswitch firmware: the hardware layer for the ATmega2560 at 16 MHz (Arduino Mega 2560).
 *
 * Pins: sensor A on ICP4 (PL0, D49), sensor B on ICP5 (PL1, D48), both active low with the
 * internal pull-up (an open-collector or slotted-optical sensor pulls the line low when the mover
 * is there); drive enable on OC4A (PH3, D6), active high; direction on PH4 (D7), 0 = on (A to
 * B), 1 = off (B to A). USART0 (the USB bridge on the Mega) at 1,000,000 baud 8N1.
 *
 * Timers (docs/firmware.md): timers 4 and 5 run in normal mode from the same prescaler at clk/8,
 * 0.5 us a tick, started together (GTCCR TSM), so TCNT4 == TCNT5 always and one extension
 * counter serves both capture units. clock_ovf counts timer 4 overflows; the 32-bit protocol
 * clock is (clock_ovf << 15) + (TCNT >> 1) microseconds, which wraps at 2^32 us as the protocol
 * wants. The drive start is a hardware compare: OC4A set on match at command + delay. A delay
 * longer than one timer period (32.768 ms) first matches half a period before the due instant
 * (compare A pre-arm, with the pin action "clear", a no-op as the pin is low) and the interrupt of
 * that exact match moves OCR4A to the due instant with the action "set".
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>

#include "../core.h"

#define COM4A_CLEAR _BV(COM4A1)
#define COM4A_SET (_BV(COM4A1) | _BV(COM4A0))
/* A compare is armed only this many ticks (20 us) ahead; closer, the start is forced at once. */
#define MARGIN_TICKS 40
/* The main loop sleeps only when the next timeout is further than this, and sets its alarm at
 * most half a timer period ahead. */
#define WAKE_MIN_US 20
#define WAKE_MAX_TICKS 0x8000u

/* Timer 4 overflows: the high part of the clock. Named and kept so an emulator can preset it. */
volatile uint32_t clock_ovf __attribute__((used, externally_visible));

/* ---- events from interrupts to the main loop ---- */
enum { EV_START = 0, EV_EDGE_A0, EV_EDGE_A1, EV_EDGE_B0, EV_EDGE_B1 };
#define EVQ 16
static volatile uint8_t ev_kind[EVQ];
static volatile uint32_t ev_t[EVQ];
static volatile uint8_t ev_head, ev_tail;
static volatile uint8_t ev_dropped;

static inline void ev_push(uint8_t kind, uint32_t t) /* interrupts off */
{
    uint8_t h = ev_head, n = (uint8_t)((h + 1) % EVQ);
    if (n == ev_tail) {
        ev_dropped++;
        return;
    }
    ev_kind[h] = kind;
    ev_t[h] = t;
    ev_head = n;
}

/* ---- the clock ---- */
static inline uint32_t us_of(uint32_t hi, uint16_t t) { return (hi << 15) + (t >> 1); }

/* Overflow count valid for a timer value t read with interrupts off. */
static inline uint32_t hi_for(uint16_t t)
{
    uint32_t hi = clock_ovf;
    if ((TIFR4 & _BV(TOV4)) && t < 0x8000u)
        hi++; /* the overflow happened but its interrupt has not run yet */
    return hi;
}

/* clock_ovf++, naked: 30 cycles with interrupts off, from the interrupt to the end of RETI (gcc's
 * prologue and epilogue around the 32-bit increment made it 64). An arrival edge that comes as it
 * starts waits that long, and one instruction more, before its capture stub, which cuts the drive
 * 21 cycles on: about 3.4 us at worst, where it was 5.6 us, over the 5 us allowed. */
ISR(TIMER4_OVF_vect, ISR_NAKED)
{
    __asm__ __volatile__("push r24\n\t"
                         "in r24, __SREG__\n\t"
                         "push r24\n\t"
                         "lds r24, clock_ovf\n\t"
                         "inc r24\n\t"
                         "sts clock_ovf, r24\n\t"
                         "brne 1f\n\t" /* no carry: the common case */
                         "lds r24, clock_ovf+1\n\t"
                         "inc r24\n\t"
                         "sts clock_ovf+1, r24\n\t"
                         "brne 1f\n\t"
                         "lds r24, clock_ovf+2\n\t"
                         "inc r24\n\t"
                         "sts clock_ovf+2, r24\n\t"
                         "brne 1f\n\t"
                         "lds r24, clock_ovf+3\n\t"
                         "inc r24\n\t"
                         "sts clock_ovf+3, r24\n\t"
                         "1: pop r24\n\t"
                         "out __SREG__, r24\n\t"
                         "pop r24\n\t"
                         "reti\n\t");
}

/* The main loop's alarm (a timeout falls due): waking is all it does. */
EMPTY_INTERRUPT(TIMER5_COMPA_vect);

uint32_t hal_now_us(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t t = TCNT4;
    uint32_t hi = hi_for(t);
    SREG = sreg;
    return us_of(hi, t);
}

/* ---- drive ---- */
enum { CMP_IDLE = 0, CMP_PRE, CMP_FINAL };
static volatile uint8_t cmp_phase;
static volatile uint32_t cmp_pre_ticks; /* 32-bit tick instant of the pre-arm match */
static volatile uint16_t cmp_due_low;
static volatile uint32_t cmp_due_us;
volatile uint8_t stop_mask __attribute__((used, externally_visible)); /* read by the capture stubs */
static volatile uint8_t dest_mask; /* bit 0 sensor A, bit 1 sensor B */
static volatile uint8_t drive_on;

static inline void drive_cut(void) /* interrupts off */
{
    TCCR4A = COM4A_CLEAR;
    TCCR4C = _BV(FOC4A); /* force the compare action now: OC4A low */
    TIMSK4 &= (uint8_t)~_BV(OCIE4A);
    cmp_phase = CMP_IDLE;
    stop_mask = 0;
    drive_on = 0;
}

ISR(TIMER4_COMPA_vect)
{
    if (cmp_phase == CMP_PRE) {
        uint16_t t = TCNT4;
        uint32_t now = (hi_for(t) << 16) | t;
        uint32_t match = now - (uint16_t)(t - OCR4A);
        if (match == cmp_pre_ticks) {
            OCR4A = cmp_due_low; /* half a period ahead: the next match is the due instant */
            TCCR4A = COM4A_SET;
            cmp_phase = CMP_FINAL;
        }
    } else if (cmp_phase == CMP_FINAL) {
        /* The hardware set OC4A at the match: the drive is on. */
        stop_mask = dest_mask;
        drive_on = 1;
        cmp_phase = CMP_IDLE;
        TIMSK4 &= (uint8_t)~_BV(OCIE4A);
        ev_push(EV_START, cmp_due_us);
    }
}

void hal_drive_schedule(uint32_t due_us, uint8_t direction, uint8_t dest)
{
    if (direction)
        PORTH |= _BV(PH4);
    else
        PORTH &= (uint8_t)~_BV(PH4);
    uint8_t sreg = SREG;
    cli();
    dest_mask = (uint8_t)(1u << dest);
    uint16_t t = TCNT4;
    uint32_t hi = hi_for(t);
    uint32_t now_ticks = (hi << 16) | t;
    int32_t dus = (int32_t)(due_us - us_of(hi, t));
    uint32_t due_ticks = (now_ticks & ~1UL) + 2UL * (uint32_t)dus;
    int32_t dt = (int32_t)(due_ticks - now_ticks);
    if (dt < MARGIN_TICKS) {
        /* Too close to arm a compare, or already past: spin to the instant, then force it. */
        while (dt > 0) {
            t = TCNT4;
            dt = (int32_t)(due_ticks - ((hi_for(t) << 16) | t));
        }
        TCCR4A = COM4A_SET;
        TCCR4C = _BV(FOC4A);
        t = TCNT4;
        uint32_t now_us = us_of(hi_for(t), t);
        stop_mask = dest_mask;
        drive_on = 1;
        ev_push(EV_START, (int32_t)(now_us - due_us) > 0 ? now_us : due_us);
    } else if (dt <= 0xFFFF) {
        OCR4A = (uint16_t)due_ticks;
        TIFR4 = _BV(OCF4A);
        TCCR4A = COM4A_SET;
        cmp_due_us = due_us;
        cmp_phase = CMP_FINAL;
        TIMSK4 |= _BV(OCIE4A);
    } else {
        cmp_pre_ticks = due_ticks - 0x8000UL;
        cmp_due_low = (uint16_t)due_ticks;
        OCR4A = (uint16_t)cmp_pre_ticks;
        TIFR4 = _BV(OCF4A);
        TCCR4A = COM4A_CLEAR; /* the pin is low: "clear on match" does nothing */
        cmp_due_us = due_us;
        cmp_phase = CMP_PRE;
        TIMSK4 |= _BV(OCIE4A);
    }
    SREG = sreg;
}

void hal_drive_off(void)
{
    uint8_t sreg = SREG;
    cli();
    drive_cut();
    SREG = sreg;
}

uint8_t hal_drive_is_on(void) { return drive_on; }

uint8_t hal_sensors(void)
{
    uint8_t pins = PINL;
    return (uint8_t)((pins & _BV(PL0) ? 0 : 1) | (pins & _BV(PL1) ? 0 : 2));
}

/* ---- input capture: sensor A on ICP4, sensor B on ICP5 ----
 * Each vector is a naked stub that cuts the drive in its first instructions when the edge is
 * the armed arrival (about 25 cycles, 1.6 us, from the edge), then jumps to the full handler,
 * which stamps and queues the edge (and finishes the cut's bookkeeping). */
#define CAPTURE_STUB(vec, tccrb, ices, maskbit, tail)                                            \
    ISR(vec, ISR_NAKED)                                                                         \
    {                                                                                            \
        __asm__ __volatile__("push r24\n\t"                                                      \
                             "in r24, __SREG__\n\t"                                             \
                             "push r24\n\t"                                                      \
                             "lds r24, %[tb]\n\t"                                                \
                             "sbrc r24, %[ic]\n\t"                                               \
                             "rjmp 1f\n\t" /* rising: released, not an arrival */               \
                             "lds r24, stop_mask\n\t"                                            \
                             "sbrs r24, %[mb]\n\t"                                               \
                             "rjmp 1f\n\t"                                                       \
                             "ldi r24, %[clr]\n\t"                                               \
                             "sts %[ta], r24\n\t"                                                \
                             "ldi r24, %[foc]\n\t"                                               \
                             "sts %[tc], r24\n\t" /* OC4A low now */                           \
                             "1: pop r24\n\t"                                                    \
                             "out __SREG__, r24\n\t"                                             \
                             "pop r24\n\t"                                                       \
                             "jmp " #tail "\n\t" ::[tb] "n"(_SFR_MEM_ADDR(tccrb)),               \
                             [ic] "n"(ices), [mb] "n"(maskbit), [clr] "n"(COM4A_CLEAR),          \
                             [ta] "n"(_SFR_MEM_ADDR(TCCR4A)), [foc] "n"(_BV(FOC4A)),             \
                             [tc] "n"(_SFR_MEM_ADDR(TCCR4C)));                                  \
    }

void __vector_capt4_tail(void) __attribute__((signal, used, externally_visible));
void __vector_capt5_tail(void) __attribute__((signal, used, externally_visible));
CAPTURE_STUB(TIMER4_CAPT_vect, TCCR4B, ICES4, 0, __vector_capt4_tail)
CAPTURE_STUB(TIMER5_CAPT_vect, TCCR5B, ICES5, 1, __vector_capt5_tail)

void __vector_capt4_tail(void)
{
    uint8_t active = !(TCCR4B & _BV(ICES4)); /* falling edge captured: the sensor went active */
    if (active && (stop_mask & 1))
        drive_cut(); /* STOP_ON_ARRIVAL: the stub has cut the pin, this the state */
    uint16_t icr = ICR4;
    TCCR4B ^= _BV(ICES4);
    TIFR4 = _BV(ICF4); /* required after changing the edge (datasheet 17.6.3) */
    ev_push(active ? EV_EDGE_A1 : EV_EDGE_A0, us_of(hi_for(icr), icr));
}

void __vector_capt5_tail(void)
{
    uint8_t active = !(TCCR5B & _BV(ICES5));
    if (active && (stop_mask & 2))
        drive_cut();
    uint16_t icr = ICR5;
    TCCR5B ^= _BV(ICES5);
    TIFR5 = _BV(ICF5);
    ev_push(active ? EV_EDGE_B1 : EV_EDGE_B0, us_of(hi_for(icr), icr)); /* TCNT5 == TCNT4 */
}

/* ---- USART0 ---- */
#define RXQ 128
#define TXQ 256
static volatile uint8_t rx_buf[RXQ];
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t tx_buf[TXQ];
static volatile uint8_t tx_head, tx_tail;

/* The USART vectors (25, 26) outrank the capture vectors (41, 46): each UART handler clears its
 * own source and re-enables interrupts at once, so an arrival edge's stub preempts it and the
 * drive is cut within ~2 us even under UART traffic. Neither can nest in itself: a byte takes
 * 10 us to arrive, and the UDRE handler keeps its interrupt off until it is done. */
ISR(USART0_RX_vect)
{
    uint8_t b = UDR0; /* clears RXC0 */
    sei();
    uint8_t n = (uint8_t)((rx_head + 1) % RXQ);
    if (n != rx_tail) {
        rx_buf[rx_head] = b;
        rx_head = n;
    } /* else lost: the frame fails COBS/CRC and is counted */
}

ISR(USART0_UDRE_vect)
{
    UCSR0B &= (uint8_t)~_BV(UDRIE0);
    sei();
    uint8_t t = tx_tail;
    if (t == tx_head)
        return;
    UDR0 = tx_buf[t];
    tx_tail = (uint8_t)(t + 1); /* TXQ == 256: wraps by itself */
    cli();
    UCSR0B |= _BV(UDRIE0);
}

void hal_tx(const uint8_t *buf, uint8_t len)
{
    while (len--) {
        uint8_t n = (uint8_t)(tx_head + 1);
        while (n == tx_tail)
            ; /* full: the UDRE interrupt drains it (10 us a byte) */
        tx_buf[tx_head] = *buf++;
        tx_head = n;
        UCSR0B |= _BV(UDRIE0);
    }
}

/* ---- start-up and the main loop ---- */
static void hw_init(void)
{
    /* Drive and direction outputs low before the timer owns the pin. */
    PORTH &= (uint8_t)~(_BV(PH3) | _BV(PH4));
    DDRH |= _BV(PH3) | _BV(PH4);
    /* Sensors: inputs with pull-ups. */
    DDRL &= (uint8_t)~(_BV(PL0) | _BV(PL1));
    PORTL |= _BV(PL0) | _BV(PL1);

    /* Timers 4 and 5: halt the shared prescaler, configure, zero both counters, release. */
    GTCCR = _BV(TSM) | _BV(PSRSYNC);
    TCCR4A = COM4A_CLEAR;
    TCCR4C = _BV(FOC4A); /* OC4A latch low */
    TCCR5A = 0;
    /* Capture the first edge that changes the present level: falling if released (high). */
    uint8_t pins = PINL;
    TCCR4B = _BV(CS41) | ((pins & _BV(PL0)) ? 0 : _BV(ICES4));
    TCCR5B = _BV(CS51) | ((pins & _BV(PL1)) ? 0 : _BV(ICES5));
    TCNT4 = 0;
    TCNT5 = 0;
    TIFR4 = 0xFF;
    TIFR5 = 0xFF;
    TIMSK4 = _BV(TOIE4) | _BV(ICIE4);
    TIMSK5 = _BV(ICIE5);
    GTCCR = 0;

    /* USART0: 1,000,000 baud = 16 MHz / (16 * (UBRR + 1)) with UBRR = 0, exact. */
    UBRR0 = 0;
    UCSR0A = 0;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);

    set_sleep_mode(SLEEP_MODE_IDLE);
}

int main(void)
{
    MCUSR = 0;
    wdt_disable();
    hw_init();
    core_init();
    sei();
    for (;;) {
        /* Interrupt facts first, in the order they happened, then the host's bytes. */
        while (ev_tail != ev_head) {
            cli();
            uint8_t k = ev_kind[ev_tail];
            uint32_t t = ev_t[ev_tail];
            ev_tail = (uint8_t)((ev_tail + 1) % EVQ);
            sei();
            if (k == EV_START)
                core_start(t);
            else
                core_edge(k >= EV_EDGE_B0, (uint8_t)((k - EV_EDGE_A0) & 1), t);
        }
        while (rx_tail != rx_head) {
            uint8_t b = rx_buf[rx_tail];
            rx_tail = (uint8_t)((rx_tail + 1) % RXQ);
            core_rx_byte(b);
            if (ev_tail != ev_head)
                break; /* keep edges ahead of later requests */
        }
        uint32_t left_us = core_poll();
        /* Sleep (idle mode: timers, capture and the UART run) until an interrupt or the next
         * timeout. Timer 5 counts with timer 4, so its compare A is the alarm; it is set at most
         * half a period ahead, where a match cannot be taken for one a period later. An alarm
         * that comes early only runs the loop once more. */
        cli();
        if (ev_tail == ev_head && rx_tail == rx_head && left_us > WAKE_MIN_US) {
            uint16_t ticks = left_us >= WAKE_MAX_TICKS / 2 ? WAKE_MAX_TICKS : (uint16_t)(2 * left_us);
            OCR5A = (uint16_t)(TCNT5 + ticks);
            TIFR5 = _BV(OCF5A);
            TIMSK5 |= _BV(OCIE5A);
            sleep_enable();
            sei(); /* the instruction after SEI runs first: an interrupt pending now wakes it */
            sleep_cpu();
            sleep_disable();
            TIMSK5 &= (uint8_t)~_BV(OCIE5A);
        }
        sei();
    }
}
