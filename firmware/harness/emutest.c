/* A self-test image for the simavr harness: shows whether the emulator has simavr 1.6's bugs.
 * Prints over USART0 at 1,000,000 baud, then sleeps with interrupts off (simavr then stops):
 *   "tifr ok" if a pending TOV4 survives the write TIFR4 = ICF4 (the datasheet), "tifr bug" if not;
 *   "sei N": N = bits of GPIOR0 set before a pending interrupt was taken after SEI (1 is right:
 *   exactly one instruction after SEI runs first);
 *   "foc done" after FOC4A with COM4A = set, which must drive OC4A high (the harness reports
 *   the drive pin: "drive 1");
 *   "tsm ok" if timers 4 and 5, zeroed 5 ticks apart while GTCCR.TSM halts the prescaler, count
 *   in lockstep once it is released, "tsm bug" if timer 5 lags;
 *   "irq N": N = CPU cycles (timer 1 at clk/1) from a read of TCNT1 to the same read first thing in
 *   INT0's handler, the interrupt raised by the instruction after the first read (the chip's
 *   interrupt response counts 5 of them; simavr 1.6 counted none);
 *   "ien ok" if an interrupt whose flag is already up is taken when its enable bit is then written
 *   (the chip takes it: the flag is the request), "ien bug" if not (simavr 1.6 queues one only
 *   as its flag rises with the enable bit set);
 *   "porf N": MCUSR's PORF as the image starts (1 after a power-on; simavr's reset cleared it).
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdint.h>

static volatile uint8_t seen;
volatile uint8_t t_isr __attribute__((used, externally_visible));

/* First thing in the handler: timer 1's low byte (lds, push and sts leave SREG alone). */
ISR(INT0_vect, ISR_NAKED)
{
    __asm__ __volatile__("push r24\n\t"
                         "lds r24, %[t]\n\t"
                         "sts t_isr, r24\n\t"
                         "pop r24\n\t"
                         "reti\n\t" ::[t] "n"(_SFR_MEM_ADDR(TCNT1L)));
}

ISR(TIMER4_OVF_vect)
{
    seen = GPIOR0;
    TIMSK4 = 0;
}

static void put(const char *s)
{
    while (*s) {
        while (!(UCSR0A & _BV(UDRE0)))
            ;
        UDR0 = (uint8_t)*s++;
    }
}

int main(void)
{
    uint8_t porf = MCUSR & _BV(PORF);
    MCUSR = 0;
    UBRR0 = 0;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(TXEN0);

    /* 1. TIFR: wait for an overflow with interrupts off, clear only the capture flag. */
    TCCR4A = 0;
    TCCR4B = _BV(CS40);
    while (!(TIFR4 & _BV(TOV4)))
        ;
    TIFR4 = _BV(ICF4);
    put((TIFR4 & _BV(TOV4)) ? "tifr ok\n" : "tifr bug\n");

    /* 2. SEI latency: TOV4 pending and enabled; count the instructions run after SEI. */
    GPIOR0 = 0;
    TIMSK4 = _BV(TOIE4);
    TIFR4 = 0xFF;
    while (!(TIFR4 & _BV(TOV4)))
        ;
    __asm__ __volatile__("sei\n\t"
                         "sbi %0, 0\n\t"
                         "sbi %0, 1\n\t"
                         "sbi %0, 2\n\t"
                         "cli\n\t" ::"I"(_SFR_IO_ADDR(GPIOR0)));
    uint8_t n = (uint8_t)((seen & 1) + ((seen >> 1) & 1) + ((seen >> 2) & 1));
    char msg[] = "sei 0\n";
    msg[4] = (char)('0' + n);
    put(msg);

    /* 3. FOC: force a "set" compare action on OC4A, the timer stopped (no real match). */
    TCCR4B = 0;
    PORTH &= (uint8_t)~_BV(PH3);
    DDRH |= _BV(PH3);
    TCCR4A = _BV(COM4A1) | _BV(COM4A0);
    TCCR4C = _BV(FOC4A);
    put("foc done\n"); /* the harness prints "drive 1" if OC4A went high */

    /* 4. TSM: halt the prescaler, zero timer 4, wait 40 cycles (5 ticks at clk/8), zero timer 5,
     * release: both start together, so reading them back to back gives the same tick (or the next
     * one, as the reads are 2 cycles apart). */
    TCCR4A = 0; /* OC4A back to the port: the drive pin goes low */
    TCCR5A = 0;
    GTCCR = _BV(TSM) | _BV(PSRSYNC);
    TCCR4B = _BV(CS41);
    TCCR5B = _BV(CS51);
    TCNT4 = 0;
    __builtin_avr_delay_cycles(40);
    TCNT5 = 0;
    GTCCR = 0;
    uint8_t t4 = TCNT4L;
    uint8_t t5 = TCNT5L;
    put((uint8_t)(t5 - t4) <= 1 ? "tsm ok\n" : "tsm bug\n");

    /* 5. Interrupt response: INT0 on falling edge, its pin an output driven low by the instruction
     * after the first read of TCNT1. */
    TCCR1A = 0;
    TCCR1B = _BV(CS10);
    PORTD |= _BV(PD0);
    DDRD |= _BV(PD0);
    EICRA = _BV(ISC01);
    EIFR = _BV(INTF0);
    EIMSK = _BV(INT0);
    uint8_t t0;
    __asm__ __volatile__("sei\n\t"
                         "lds %0, %[t]\n\t"
                         "cbi %[port], 0\n\t"
                         "nop\n\t"
                         "nop\n\t"
                         "nop\n\t"
                         "nop\n\t"
                         "cli\n\t"
                         : "=r"(t0)
                         : [t] "n"(_SFR_MEM_ADDR(TCNT1L)), [port] "I"(_SFR_IO_ADDR(PORTD)));
    EIMSK = 0;
    uint8_t d = (uint8_t)(t_isr - t0);
    char irq[] = "irq 00\n";
    irq[4] = (char)('0' + d / 10 % 10);
    irq[5] = (char)('0' + d % 10);
    put(irq);

    /* 6. Enable after the flag: TOV4 up with TOIE4 off and interrupts on, then TOIE4 written. */
    TCCR4A = 0;
    TCCR4B = _BV(CS40);
    TIMSK4 = 0;
    seen = 0;
    GPIOR0 = 0x80;
    TIFR4 = 0xFF;
    sei();
    while (!(TIFR4 & _BV(TOV4)))
        ;
    TIMSK4 = _BV(TOIE4); /* the handler sets seen = GPIOR0 and masks itself */
    __asm__ __volatile__("nop\n\tnop\n\t");
    cli();
    put(seen == 0x80 ? "ien ok\n" : "ien bug\n");
    put(porf ? "porf 1\n" : "porf 0\n");

    while (!(UCSR0A & _BV(TXC0)))
        ;
    for (;;)
        ;
}
