/* usmswitch firmware: the hardware layer for the ATmega2560 at 16 MHz (Arduino Mega 2560).
 *
 * Pins: sensor A on ICP4 (PL0, D49), sensor B on ICP5 (PL1, D48), both active low with the
 * internal pull-up (an open-collector or slotted-optical sensor pulls the line low when the mover
 * is there); drive enable on OC4A (PH3, D6), active high; direction on PH4 (D7), 0 = on (A to
 * B), 1 = off (B to A). USART0 (the USB bridge on the Mega) at 1,000,000 baud 8N1.
 *
 * Timers (docs/firmware.md): timers 4 and 5 run in normal mode from the same prescaler at clk/8,
 * 0.5 us a tick, started together (GTCCR TSM), so TCNT4 == TCNT5 always and one extension
 * counter serves both capture units. clock_ovf counts timer 5 overflows (vector 50, below both
 * capture vectors); the 32-bit protocol clock is (clock_ovf << 15) + (TCNT >> 1) microseconds,
 * which wraps at 2^32 us as the protocol wants. A capture is stamped from ICR and the counter read
 * in its handler (the period it belongs to follows from the two), whatever ran first. The drive start is a hardware compare: OC4A set on match at command + delay. A delay
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

/* Code that runs with interrupts off is inlined whole: a call from a handler makes gcc save every
 * call-clobbered register first (the capture tail took 243 cycles so, an arrival edge behind it
 * as long). */

#define COM4A_CLEAR _BV(COM4A1)
#define COM4A_SET (_BV(COM4A1) | _BV(COM4A0))
/* A compare is armed when its match is at least this many ticks (2 us) ahead when the arming
 * section starts (which writes OCR4A within 12 cycles); closer or past, the start is forced by
 * FOC4A at its instant. */
#define ARM_MIN_TICKS 4
/* The main loop sleeps only when the next timeout is further than this, and sets its alarm at
 * most WAKE_MAX_TICKS (8.2 ms) ahead: every main-loop pass, and with it every watchdog kick,
 * then comes within that plus the longest pass. */
#define WAKE_MIN_US 20
#define WAKE_MAX_TICKS 0x4000u

/* The clock's overflow interrupt. Timer 5's (vector 50) is outranked by both capture vectors
 * (41, 46), so a capture pending beside it runs first. USMSWITCH_PLANT_STAMP_ERROR builds the test
 * image with the code before issue 23 (timer 4's, vector 45, above sensor B's 46, and the stamp's
 * period taken from ICR alone): its one-period error on sensor B is what the overflow sweep and
 * the soak must find. Never defined for the image that is flashed. */
#ifdef USMSWITCH_PLANT_STAMP_ERROR
#define CLOCK_OVF_vect TIMER4_OVF_vect
#define CLOCK_TIFR TIFR4
#define CLOCK_TOV TOV4
#else
#define CLOCK_OVF_vect TIMER5_OVF_vect
#define CLOCK_TIFR TIFR5
#define CLOCK_TOV TOV5
#endif

/* MCUSR as the chip left it at this reset (power-on, external, brown-out, watchdog, JTAG bits),
 * saved by early_init (vectors.S) before anything else runs: .noinit, so the C start-up's clearing
 * of .bss spares it. */
uint8_t reset_cause __attribute__((section(".noinit"), used, externally_visible));

/* Clock overflows: the high part of the clock. Named and kept so an emulator can preset it. */
volatile uint32_t clock_ovf __attribute__((used, externally_visible));

/* ---- events from interrupts to the main loop ----
 * An event's instant is kept as the timer gave it (the period count and the 16-bit tick); the main
 * loop makes microseconds of it, so the handlers stay short. Edges go through a ring of EVQ - 1;
 * a full ring loses the edge and counts it in ev_dropped, which the main loop reports (FAULT
 * EVENTS_LOST, PONG) and which ends a running stroke. The start has a slot of its own, so it is
 * never lost: at most one start is pending (a stroke's), and the main loop takes it before any
 * later edge. The external interrupt's cut leaves its instant in a slot of its own too. */
enum { EV_EDGE_A0 = 0, EV_EDGE_A1, EV_EDGE_B0, EV_EDGE_B1 };
#define EV_MISSED 0x04 /* the capture unit missed this edge: stamped when found (EF_MISSED) */
#define EVQ 16
static volatile uint8_t ev_kind[EVQ];
static volatile uint32_t ev_hi[EVQ];
static volatile uint16_t ev_lo[EVQ];
static volatile uint8_t ev_head, ev_tail;
static volatile uint16_t ev_dropped;
/* The main loop handles at most this many edges a pass, then the host's bytes and the timeouts:
 * a storm of edges cannot hold back a STOP, a stall or the watchdog's kick. And it takes an edge
 * only while at most TX_EDGE_BACKLOG bytes wait in the transmit ring: edges never fill it, so a
 * reply to the host waits behind at most that much (1.3 ms of the line) and a pass never waits
 * for room to send an edge. What the line cannot carry stays queued, and past the queue is lost,
 * counted and reported. */
#define EV_PER_PASS 4
#define TX_EDGE_BACKLOG 128

/* A capture unit whose edge found the ring full stays masked ("blanked": bit 0 A, bit 1 B; its
 * stub, vectors.S, leaves it so) until the main loop has emptied the ring: a line ringing faster
 * than the handlers can run would otherwise take the whole CPU (a capture costs ~13 us, a 50 kHz
 * line's edges come every 10 us), and the main loop, the host and the watchdog's kick with it.
 * The arrival's cut is the external interrupt's and does not wait; the edges of a blanked unit are
 * lost, counted as the one that found the ring full, and its pin is read back when it is unmasked. */
volatile uint8_t cap_blanked __attribute__((used, externally_visible));

/* 1: the start's instant is in start_hi/lo (a start forced by hal_drive_schedule); 2: it is the
 * due instant, cmp_due_hi/tick (the compare match's, set by vectors.S); neither is written again
 * before the main loop has taken it (the core schedules the next stroke only after). */
volatile uint8_t start_pending __attribute__((used, externally_visible));
static volatile uint32_t start_hi;
static volatile uint16_t start_lo;

/* Written by the arrival cut in vectors.S (INT4/INT5): which sensor cut (1 A, 2 B; 0 none), and
 * its instant as timer 5 and the clock had it (TCNT5, clock_ovf's low byte, TIFR5). */
volatile uint8_t cut_flag __attribute__((used, externally_visible));
volatile uint16_t cut_tick __attribute__((used, externally_visible));
volatile uint8_t cut_ovf __attribute__((used, externally_visible));
volatile uint8_t cut_tifr __attribute__((used, externally_visible));

/* Claim the next slot of the ring (interrupts off, a few cycles): its index, or EVQ when the ring
 * is full (the edge is lost and counted). The claimant fills the slot after, interrupts on: the
 * main loop, the ring's reader, runs only when every handler has returned, so a claimed slot is
 * always filled when it reads it, and a handler nested in the claimant claims the slot after. */
static inline __attribute__((always_inline)) uint8_t ev_claim(void)
{
    uint8_t h = ev_head, n = (uint8_t)(h + 1) & (EVQ - 1);
    if (n == ev_tail) {
        ev_dropped++;
        return EVQ;
    }
    ev_head = n;
    return h;
}

static inline __attribute__((always_inline)) void ev_fill(uint8_t i, uint8_t kind, uint32_t hi, uint16_t ticks)
{
    ev_kind[i] = kind;
    ev_hi[i] = hi;
    ev_lo[i] = ticks;
}

/* ---- the clock ---- */
static inline uint32_t us_of(uint32_t hi, uint16_t t) { return (hi << 15) + (t >> 1); }

/* Overflow count valid for a timer value t read with interrupts off. */
static inline __attribute__((always_inline)) uint32_t hi_for(uint16_t t)
{
    uint32_t hi = clock_ovf;
    if ((CLOCK_TIFR & _BV(CLOCK_TOV)) && t < 0x8000u)
        hi++; /* the overflow happened but its interrupt has not run yet */
    return hi;
}

/* The period of a capture: icr is the counter at the edge; t the counter, ovf the overflow count
 * and tov the clock's overflow flag, read together after it in the handler (interrupts off). The
 * edge came less than a period before t, so it is in t's period when icr <= t and in the one
 * before otherwise, whether or not the overflow's interrupt has run (issue 23: sensor B's handler,
 * outranked by timer 4's overflow, took icr's period from the flag the overflow handler had
 * already cleared, one period late). */
static inline __attribute__((always_inline)) uint32_t capture_period(uint16_t icr, uint16_t t, uint32_t ovf,
                                                                      uint8_t tov)
{
#ifdef USMSWITCH_PLANT_STAMP_ERROR
    (void)t;
    return ovf + (tov && icr < 0x8000u);
#else
    uint32_t hi = ovf + (tov && t < 0x8000u);
    return icr <= t ? hi : hi - 1;
#endif
}

/* The clock's overflow interrupt (clock_ovf++, 30 cycles) is in vectors.S, below both capture
 * vectors: a capture pending beside it always runs first. */

/* The main loop's alarm (a timeout falls due, timer 5's compare A) is a bare RETI in vectors.S:
 * waking is all it does. */

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
volatile uint8_t cmp_phase __attribute__((used, externally_visible)); /* CMP_*: vectors.S reads it */
static volatile uint16_t cmp_pre_period; /* the timer period of the pre-arm match (low 16 bits) */
static volatile uint16_t cmp_due_low;
static volatile uint32_t cmp_due_hi; /* the due instant as an event stamp (period, tick) */
static volatile uint16_t cmp_due_tick;
volatile uint8_t stop_mask __attribute__((used, externally_visible)); /* read by the capture stubs */
volatile uint8_t dest_mask __attribute__((used, externally_visible)); /* bit 0 sensor A, bit 1 B */
volatile uint8_t drive_on __attribute__((used, externally_visible)); /* cleared by the cut too */

static inline __attribute__((always_inline)) void drive_cut(void) /* interrupts off */
{
    TCCR4A = COM4A_CLEAR;
    TCCR4C = _BV(FOC4A); /* force the compare action now: OC4A low */
    TIMSK4 &= (uint8_t)~_BV(OCIE4A);
    cmp_phase = CMP_IDLE;
    stop_mask = 0;
    drive_on = 0;
}

/* An arrival between the drive going on and stop_mask being set found the external interrupt
 * disarmed: look at the sensor as stop_mask is set, and cut now if it is there (interrupts off).
 * (The compare match's own path, in vectors.S, does the same in its first cycles.) */
static inline __attribute__((always_inline)) void arm_arrival_cut(void)
{
    stop_mask = dest_mask;
    drive_on = 1;
    if (!(PINL & dest_mask)) { /* active low: the mover is at the destination already */
        drive_cut();
        cut_tick = TCNT5;
        cut_ovf = (uint8_t)clock_ovf;
        cut_tifr = CLOCK_TIFR;
        cut_flag = dest_mask;
    }
}

/* The start's compare at its pre-arm match, half a period before the start (TIMER4_COMPA_vect in
 * vectors.S jumps here; the final match, the drive going on, is all its own): interrupts off
 * throughout, the drive off, so its length holds back no arrival's cut. It moves OCR4A to the due
 * instant. */
void __vector_compare_rest(void) __attribute__((signal, used, externally_visible));
void __vector_compare_rest(void)
{
    if (cmp_phase == CMP_PRE) {
        /* the period of this match: t's, or the one before when the counter has wrapped since
         * (16 bits of it: the pre-arm is at most 30 periods ahead) */
        uint16_t t = TCNT4;
        uint16_t ocr = OCR4A;
        uint16_t hi = (uint16_t)clock_ovf + ((CLOCK_TIFR & _BV(CLOCK_TOV)) && t < 0x8000u);
        if (ocr > t)
            hi--;
        if (hi == cmp_pre_period) {
            OCR4A = cmp_due_low; /* half a period ahead: the next match is the due instant */
            TCCR4A = COM4A_SET;
            cmp_phase = CMP_FINAL;
        }
    }
}

void hal_drive_schedule(uint32_t due_us, uint8_t direction, uint8_t dest)
{
    if (direction)
        PORTH |= _BV(PH4);
    else
        PORTH &= (uint8_t)~_BV(PH4);
    /* No stroke runs and no compare is armed here (the core schedules only when idle), so the
     * arithmetic runs with interrupts on; only the clock read and the arming are atomic. */
    dest_mask = (uint8_t)(1u << dest);
    cmp_due_hi = due_us >> 15; /* the START stamp, made here rather than in the handler */
    cmp_due_tick = (uint16_t)(due_us << 1);
    uint8_t sreg = SREG;
    cli();
    uint16_t t0 = TCNT4;
    uint32_t hi = hi_for(t0);
    SREG = sreg;
    uint32_t now_ticks = (hi << 16) | t0;
    int32_t dus = (int32_t)(due_us - us_of(hi, t0));
    uint32_t due_ticks = (now_ticks & ~1UL) + 2UL * (uint32_t)dus;
    int32_t dt = (int32_t)(due_ticks - now_ticks); /* from t0 */
    if (dt > 0xFFFF) {
        /* Further than a period: the pre-arm match half a period before, hours of margin. */
        uint32_t pre_ticks = due_ticks - 0x8000UL;
        cmp_pre_period = (uint16_t)(pre_ticks >> 16);
        cmp_due_low = (uint16_t)due_ticks;
        cli();
        OCR4A = (uint16_t)pre_ticks;
        TIFR4 = _BV(OCF4A);
        TCCR4A = COM4A_CLEAR; /* the pin is low: "clear on match" does nothing */
        cmp_phase = CMP_PRE;
        TIMSK4 |= _BV(OCIE4A);
        SREG = sreg;
        return;
    }
    cli();
    if (dt - (int32_t)(uint16_t)(TCNT4 - t0) >= ARM_MIN_TICKS) {
        /* The match is still ahead by the margin: the hardware sets OC4A at the exact tick. */
        OCR4A = (uint16_t)due_ticks;
        TIFR4 = _BV(OCF4A);
        TCCR4A = COM4A_SET;
        cmp_phase = CMP_FINAL;
        TIMSK4 |= _BV(OCIE4A);
        SREG = sreg;
        return;
    }
    SREG = sreg;
    /* Due within the margin, or past: wait for the instant with interrupts on (at most
     * ARM_MIN_TICKS; each read of the counter atomic), then force OC4A high; START says how late. */
    for (;;) {
        cli();
        uint16_t e = (uint16_t)(TCNT4 - t0);
        SREG = sreg;
        if (dt - (int32_t)e <= 0)
            break;
    }
    cli();
    TCCR4A = COM4A_SET;
    TCCR4C = _BV(FOC4A);
    uint16_t t = TCNT4;
    uint32_t hi_now = hi_for(t);
    arm_arrival_cut();
    SREG = sreg;
    /* START: the instant it went on when that was after the due one (late), else the due one */
    uint32_t s_hi = cmp_due_hi;
    uint16_t s_tick = cmp_due_tick;
    if ((int32_t)(us_of(hi_now, t) - due_us) > 0) {
        s_hi = hi_now;
        s_tick = t;
    }
    cli();
    start_hi = s_hi;
    start_lo = s_tick;
    start_pending = 1;
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
 * The arrival's cut is the external interrupt's (INT4/INT5, vectors.S; the same sensor lines on
 * PE4/PE5: that wiring is required). Each capture vector's stub (vectors.S) masks its own unit
 * (ICIEn), turns interrupts on and calls its tail here; the stub turns them off again, unmasks
 * the unit and returns, so a tail never nests in itself, and the cuts, the UART and the other
 * unit are held back only by the short interrupts-off sections below.
 *
 * The tail reads the capture, the counter and the clock together, flips the edge select for the
 * opposite edge and clears ICFn (the datasheet requires it after changing the edge), then reads
 * the pin back: a pin already at the opposite level with no capture pending means that edge came
 * before the flip (a pulse shorter than the handler's latency) and the unit would wait for an
 * edge that has happened. Then the edge select goes back, and the missed edge is queued too,
 * stamped with the counter read here and flagged (EV_MISSED). The main loop also compares the
 * pins with the levels it last reported, for what no handler saw. An edge of the other sensor
 * may be queued first; the main loop puts the two back in the order of their stamps. */
#define CAPTURE_TAIL(name, icr_reg, tcnt_reg, tccrb, ices, tifr, icf, pinbit, kind0)               \
    void name(void) __attribute__((used, externally_visible));                                   \
    void name(void) /* interrupts on, this unit masked */                                          \
    {                                                                                              \
        cli();                                                                                     \
        uint16_t icr = icr_reg;                                                                    \
        uint16_t t = tcnt_reg;                                                                     \
        uint32_t ovf = clock_ovf;                                                                  \
        uint8_t tov = CLOCK_TIFR & _BV(CLOCK_TOV);                                                 \
        sei(); /* two short sections rather than one: the cut waits for neither long */          \
        cli();                                                                                     \
        uint8_t b = tccrb;                                                                         \
        uint8_t active = !(b & _BV(ices)); /* falling edge captured: the sensor went active */     \
        tccrb = b ^ _BV(ices);                                                                     \
        tifr = _BV(icf); /* required after changing the edge (datasheet 17.6.3) */                 \
        uint8_t missed = 0;                                                                        \
        if ((uint8_t)!(PINL & _BV(pinbit)) != active && !(tifr & _BV(icf))) {                     \
            tccrb = b; /* the opposite edge came already: wait for the one after it */              \
            tifr = _BV(icf);                                                                       \
            missed = 1;                                                                            \
        }                                                                                          \
        sei();                                                                                     \
        cli();                                                                                     \
        uint8_t i = ev_claim();                                                                    \
        uint8_t i2 = missed ? ev_claim() : EVQ;                                                    \
        if (i == EVQ || (missed && i2 == EVQ))                                                     \
            cap_blanked |= (uint8_t)(kind0 ? 2 : 1); /* the ring is full: mask it till it empties */ \
        sei();                                                                                     \
        uint32_t hi = capture_period(icr, t, ovf, tov);                                            \
        if (i != EVQ)                                                                              \
            ev_fill(i, (uint8_t)((kind0) + active), hi, icr);                                      \
        if (i2 != EVQ)                                                                             \
            ev_fill(i2, (uint8_t)(((kind0) + !active) | EV_MISSED), ovf + (tov && t < 0x8000u), t); \
    }

CAPTURE_TAIL(capture_a_tail, ICR4, TCNT4, TCCR4B, ICES4, TIFR4, ICF4, PL0, EV_EDGE_A0)
CAPTURE_TAIL(capture_b_tail, ICR5, TCNT5, TCCR5B, ICES5, TIFR5, ICF5, PL1, EV_EDGE_B0)

/* ---- USART0 ----
 * The rings are filled and drained by the two USART handlers in vectors.S. Each masks its own
 * interrupt (RXCIE0, UDRIE0) and turns interrupts on, then off again before it unmasks itself
 * and returns: neither nests in itself, and an arrival's cut waits little for them. */
#define RXQ 128 /* vectors.S wraps rx_head with & 0x7F */
#define TXQ 256 /* and tx_tail as a byte */
volatile uint8_t rx_buf[RXQ] __attribute__((used, externally_visible));
volatile uint8_t rx_head __attribute__((used, externally_visible)), rx_tail __attribute__((used, externally_visible));
volatile uint8_t tx_buf[TXQ] __attribute__((used, externally_visible));
volatile uint8_t tx_head __attribute__((used, externally_visible)), tx_tail __attribute__((used, externally_visible));

void hal_tx(const uint8_t *buf, uint8_t len)
{
    while (len--) {
        uint8_t n = (uint8_t)(tx_head + 1);
        while (n == tx_tail)
            ; /* full: the UDRE interrupt drains it (10 us a byte) */
        tx_buf[tx_head] = *buf++;
        tx_head = n;
        uint8_t sreg = SREG;
        cli(); /* the handlers mask and unmask themselves in UCSR0B */
        UCSR0B |= _BV(UDRIE0);
        SREG = sreg;
    }
}

/* ---- start-up and the main loop ---- */
static void hw_init(void)
{
    /* Drive and direction outputs low before the timer owns the pin. */
    PORTH &= (uint8_t)~(_BV(PH3) | _BV(PH4));
    DDRH |= _BV(PH3) | _BV(PH4);
    /* Sensors: inputs with pull-ups; each line also on an external interrupt pin (A: PE4/INT4, D2;
     * B: PE5/INT5, D3), falling edge (the sensor goes active): the arrival's cut. */
    DDRL &= (uint8_t)~(_BV(PL0) | _BV(PL1));
    PORTL |= _BV(PL0) | _BV(PL1);
    DDRE &= (uint8_t)~(_BV(PE4) | _BV(PE5));
    PORTE |= _BV(PE4) | _BV(PE5);
    EICRB = _BV(ISC41) | _BV(ISC51);
    EIFR = _BV(INTF4) | _BV(INTF5);
    EIMSK = _BV(INT4) | _BV(INT5);

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
#ifdef USMSWITCH_PLANT_STAMP_ERROR
    TIMSK4 = _BV(TOIE4) | _BV(ICIE4);
    TIMSK5 = _BV(ICIE5);
#else
    TIMSK4 = _BV(ICIE4);
    TIMSK5 = _BV(TOIE5) | _BV(ICIE5);
#endif
    GTCCR = 0;

    /* USART0: 1,000,000 baud = 16 MHz / (16 * (UBRR + 1)) with UBRR = 0, exact. */
    UBRR0 = 0;
    UCSR0A = 0;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);

    set_sleep_mode(SLEEP_MODE_IDLE);
}

/* The instant of the pending start (written whole before start_pending, and not again until the
 * core has it). */
static uint32_t start_instant(void)
{
    return start_pending == 2 ? us_of(cmp_due_hi, cmp_due_tick) : us_of(start_hi, start_lo);
}

/* The levels the main loop last reported for each sensor (bit 0 A, bit 1 B, 1 active). */
static uint8_t reported;

/* The microsecond stamp of an event slot. */
static uint32_t ev_us(uint8_t i) { return us_of(ev_hi[i], ev_lo[i]); }

/* One edge to the core, and what the host now knows of the sensor. */
static void report_edge(uint8_t ch, uint8_t level, uint32_t t, uint8_t flags)
{
    reported = (uint8_t)((reported & ~(1u << ch)) | (level << ch));
    core_edge(ch, level, t, flags);
}

/* A pin whose level differs from the one last reported, with no capture pending and no edge
 * queued (looked at with interrupts off, the pin first: an edge after that look has set its flag
 * by the next): the capture unit missed the edge. It is set again for the edge after the pin's
 * level, and the edge reported, stamped now and flagged. Constant masks: a short cli section. */
static inline __attribute__((always_inline)) void check_pin(uint8_t ch)
{
    uint8_t bit = ch ? _BV(PL1) : _BV(PL0);
    cli();
    uint8_t level = !(PINL & bit);
    uint8_t pending = ch ? (TIFR5 & _BV(ICF5)) : (TIFR4 & _BV(ICF4));
    if (pending || ev_tail != ev_head || level == !!(reported & bit)) {
        sei();
        return;
    }
    /* capture the next change from this level: rising (released) when active */
    if (ch) {
        TCCR5B = level ? (uint8_t)(TCCR5B | _BV(ICES5)) : (uint8_t)(TCCR5B & ~_BV(ICES5));
        TIFR5 = _BV(ICF5);
    } else {
        TCCR4B = level ? (uint8_t)(TCCR4B | _BV(ICES4)) : (uint8_t)(TCCR4B & ~_BV(ICES4));
        TIFR4 = _BV(ICF4);
    }
    sei();
    report_edge(ch, level, hal_now_us(), EF_MISSED);
}

/* What no handler saw: an arrival the external interrupt cut with no capture of it, and a pin
 * whose level differs from the one last reported with no capture pending (both read with
 * interrupts off, so a capture cannot come between the look at its flag and at the pin). The
 * capture unit is set again for the edge after the pin's level. Only when every queued edge
 * older than what is looked at has been handled. */
static void check_lines(void)
{
    cli();
    uint8_t f = cut_flag;
    uint16_t tick = cut_tick;
    uint8_t ovf = cut_ovf, tifr = cut_tifr;
    uint8_t cut_pending = (f & 2) ? (TIFR5 & _BV(ICF5)) : (TIFR4 & _BV(ICF4));
    sei();
    if (f && !cut_pending) {
        uint8_t ch = f >> 1;
        uint32_t now_ovf;
        cli();
        now_ovf = clock_ovf;
        sei();
        /* the period: the one now, less what passed since (under 2^8 periods, 8.4 s) */
        uint32_t hi = now_ovf - (uint8_t)((uint8_t)now_ovf - ovf);
        uint32_t t = us_of(hi + ((tifr & _BV(CLOCK_TOV)) && tick < 0x8000u), tick);
        if (ev_tail == ev_head || (int32_t)(ev_us(ev_tail) - t) > 0) {
            cut_flag = 0; /* no other cut comes: the stub disarmed itself */
            /* the stroke's arrival came with no capture of it: the cut's instant is its stamp */
            if (core_wants_arrival(ch))
                report_edge(ch, 1, t, EF_MISSED | EF_CUT);
        }
    }
    if (ev_tail != ev_head)
        return;
    check_pin(0);
    check_pin(1);
}

int main(void)
{
    hw_init();
    core_init();
    reported = hal_sensors();
    sei();
    core_boot(reset_cause);
    uint16_t dropped_seen = 0;
    for (;;) {
        /* The watchdog's only kick: a pass of this loop that does not come round within the
         * watchdog's period (32 ms; the longest pass is the 8.2 ms alarm, or a few frames' wait for
         * room in the transmit ring) resets the chip, and the reset takes the drive pin low. */
        wdt_reset();
        /* Interrupt facts first, in the order they happened, at most EV_PER_PASS edges, then the
         * host's bytes and the timeouts. The slot at ev_tail was written whole before its producer
         * (interrupts off) moved ev_head past it, and no producer writes it again before ev_tail
         * moves on: no cli needed to read it. */
        for (uint8_t n = 0; n < EV_PER_PASS; n++) {
            uint8_t i = ev_tail;
            uint8_t have = i != ev_head;
            if (start_pending) {
                uint32_t ts = start_instant();
                if (!have || (int32_t)(ev_us(i) - ts) >= 0) {
                    start_pending = 0;
                    core_start(ts);
#ifdef USMSWITCH_TEST_HANG_ON_START
                    for (;;)
                        ; /* test image only: the main loop hangs mid-stroke, the drive on */
#endif
                    continue;
                }
            }
            if (!have || (uint8_t)(tx_head - tx_tail) > TX_EDGE_BACKLOG)
                break;
            uint8_t j = (uint8_t)(i + 1) & (EVQ - 1);
            if (j != ev_head && (int32_t)(ev_us(j) - ev_us(i)) < 0) {
                /* an edge queued from inside the other sensor's handler, before that one's: swap
                 * (both slots are published; no producer touches them) */
                uint8_t k2 = ev_kind[j];
                uint32_t h2 = ev_hi[j];
                uint16_t l2 = ev_lo[j];
                ev_kind[j] = ev_kind[i];
                ev_hi[j] = ev_hi[i];
                ev_lo[j] = ev_lo[i];
                ev_kind[i] = k2;
                ev_hi[i] = h2;
                ev_lo[i] = l2;
            }
            uint8_t k = ev_kind[i];
            uint32_t t = ev_us(i);
            ev_tail = j;
            report_edge((uint8_t)((k >> 1) & 1), (uint8_t)(k & 1), t, (k & EV_MISSED) ? EF_MISSED : 0);
        }
        /* A blanked capture unit is unmasked once the ring is empty (a capture pending since is
         * then taken, its pin read back). */
        if (cap_blanked && ev_tail == ev_head) {
            cli();
            if (cap_blanked & 1)
                TIMSK4 |= _BV(ICIE4);
            if (cap_blanked & 2)
                TIMSK5 |= _BV(ICIE5);
            cap_blanked = 0;
            sei();
        }
        /* Lost edges: reported, and a running stroke ends. */
        cli();
        uint16_t dropped = ev_dropped;
        sei();
        if (dropped != dropped_seen) {
            if (start_pending) {
                /* the start first, whatever its place among the edges still queued: the stroke
                 * the loss ends has started */
                uint32_t ts = start_instant();
                start_pending = 0;
                core_start(ts);
            }
            core_events_lost((uint16_t)(dropped - dropped_seen), hal_now_us());
            dropped_seen = dropped;
        }
        if (!start_pending)
            check_lines();
        /* At most one frame a pass, so a pass stays short under a flood of requests. */
        while (rx_tail != rx_head) {
            uint8_t b = rx_buf[rx_tail];
            rx_tail = (uint8_t)((rx_tail + 1) % RXQ);
            core_rx_byte(b);
            if (b == 0)
                break; /* a frame done */
        }
        uint32_t left_us = core_poll();
        /* Sleep (idle mode: timers, capture and the UART run) until an interrupt or the next
         * timeout. Timer 5 counts with timer 4, so its compare A is the alarm; it is set at most
         * WAKE_MAX_TICKS ahead, where a match cannot be taken for one a period later. An alarm
         * that comes early only runs the loop once more. Only the last look at the queues and the
         * 16-bit timer access are under cli. */
        if (left_us <= WAKE_MIN_US)
            continue;
        uint16_t ticks = left_us >= WAKE_MAX_TICKS / 2 ? WAKE_MAX_TICKS : (uint16_t)(2 * left_us);
        cli();
        /* (a lost edge leaves the queue full: no need to look at ev_dropped) */
        if (ev_tail == ev_head && rx_tail == rx_head && !(start_pending | cut_flag)) {
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
