/* usmswitch firmware: the code that is counted in cycles, written out (avr-gcc cannot give a
 * naked function a stack usage, and these are assembly in all but name): the first code after
 * reset, the clock's overflow interrupt and the two capture stubs. docs/firmware.md lists their
 * cycles with interrupts off. */
#include <avr/io.h>

/* .init3, before .data and .bss are set up, interrupts off since the reset: keep MCUSR (the
 * reset's cause) in reset_cause (.noinit), clear it (a watchdog reset leaves WDRF set, and WDRF
 * forces the watchdog on at its shortest period, 16 ms, until it is cleared), then run the
 * watchdog at 32 ms (WDP0, the datasheet's "32 ms" at 5 V; WDCE+WDE, then the new value within
 * four cycles). From here on only the main loop kicks it. */
    .section .init3,"ax",@progbits
    .global early_init
early_init:
    in r24, _SFR_IO_ADDR(MCUSR)
    sts reset_cause, r24
    out _SFR_IO_ADDR(MCUSR), r1 /* r1 is zero from .init2 */
    ldi r24, _BV(WDCE) | _BV(WDE)
    ldi r25, _BV(WDE) | _BV(WDP0)
    wdr
    sts _SFR_MEM_ADDR(WDTCSR), r24
    sts _SFR_MEM_ADDR(WDTCSR), r25

    .text

/* clock_ovf++: 30 cycles with interrupts off, from the interrupt to the end of RETI. Timer 5's
 * overflow (vector 50), below both capture vectors; USMSWITCH_PLANT_STAMP_ERROR (a test image)
 * puts it back on timer 4's (vector 45, above sensor B's 46), as it was before issue 23. */
#ifdef USMSWITCH_PLANT_STAMP_ERROR
    .global TIMER4_OVF_vect
TIMER4_OVF_vect:
#else
    .global TIMER5_OVF_vect
TIMER5_OVF_vect:
#endif
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    lds r24, clock_ovf
    inc r24
    sts clock_ovf, r24
    brne 1f /* no carry: the common case */
    lds r24, clock_ovf+1
    inc r24
    sts clock_ovf+1, r24
    brne 1f
    lds r24, clock_ovf+2
    inc r24
    sts clock_ovf+2, r24
    brne 1f
    lds r24, clock_ovf+3
    inc r24
    sts clock_ovf+3, r24
1:  pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti

/* The main loop's alarm (timer 5's compare A): waking the CPU is all it does. */
    .global TIMER5_COMPA_vect
TIMER5_COMPA_vect:
    reti

/* OC4A (the drive) cleared on a forced compare: the pin is low at the end of this. Uses r24. */
.macro DRIVE_OFF_NOW
    ldi r24, _BV(COM4A1)
    sts _SFR_MEM_ADDR(TCCR4A), r24
    ldi r24, _BV(FOC4A)
    sts _SFR_MEM_ADDR(TCCR4C), r24 /* OC4A low now */
.endm

/* The arrival's cut. Each sensor's line is also on an external interrupt pin (A: INT4, PE4, D2;
 * B: INT5, PE5, D3), falling edge: the sensor goes active. Vectors 5 and 6 outrank every other, so
 * only an interrupts-off stretch already running holds one back, never another handler's turn.
 * When the sensor is the armed arrival's (stop_mask) it sets COM4A to "clear" and strobes FOC4A:
 * OC4A is low 19 cycles after the vector (5 to enter, 3 for its jmp, 11 here). No instruction
 * here changes SREG, so it is not saved. */
.macro ARRIVAL_CUT maskbit
    push r24
    lds r24, stop_mask
    sbrs r24, \maskbit
    rjmp 1f
    DRIVE_OFF_NOW
1:  pop r24
    reti
.endm

    .global INT4_vect
INT4_vect:
    ARRIVAL_CUT 0

    .global INT5_vect
INT5_vect:
    ARRIVAL_CUT 1

/* A capture vector's first instructions cut the drive again when the edge is the armed arrival
 * (the falling edge, active low, of the sensor in stop_mask): the cut of a board whose sensors are
 * not wired to INT4/INT5 as well, or one the external interrupt missed. Then the tail (board.c)
 * stamps and queues the edge, with interrupts on. No instruction here changes SREG. */
.macro CAPTURE_STUB tccrb, ices, maskbit, tail
    push r24
    lds r24, \tccrb
    sbrc r24, \ices
    rjmp 1f /* rising: released, not an arrival */
    lds r24, stop_mask
    sbrs r24, \maskbit
    rjmp 1f
    DRIVE_OFF_NOW
1:  pop r24
    jmp \tail
.endm

    .global TIMER4_CAPT_vect
TIMER4_CAPT_vect:
    CAPTURE_STUB _SFR_MEM_ADDR(TCCR4B), ICES4, 0, __vector_capt4_tail

    .global TIMER5_CAPT_vect
TIMER5_CAPT_vect:
    CAPTURE_STUB _SFR_MEM_ADDR(TCCR5B), ICES5, 1, __vector_capt5_tail

/* USART0 receive. With interrupts off it claims the ring's next slot (rx_head moves on) and reads
 * the byte (which clears RXC0 for it); then interrupts are on again, 31 cycles after the vector,
 * and the byte goes into its slot. A second byte already in the USART's two-byte buffer (this
 * handler was held back more than a byte time) sets RXC0 again at once and enters this handler
 * again, nested: it claims the slot after, so the ring keeps the bytes in order (the handler before
 * issue 23 moved rx_head after its sei, and a nested byte overwrote the one before it: a frame lost
 * after each long interrupts-off stretch). The main loop, the ring's reader, runs only when every
 * handler has returned, so a claimed slot is always filled when it reads it. A full ring (128
 * bytes) loses the byte; its frame then fails COBS or CRC and is counted. */
    .global USART0_RX_vect
USART0_RX_vect:
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    push r25
    push r30
    lds r30, rx_head
    mov r25, r30
    inc r25
    andi r25, 0x7F /* RXQ = 128 */
    lds r24, rx_tail
    cp r25, r24
    breq 2f /* full */
    sts rx_head, r25
    lds r24, _SFR_MEM_ADDR(UDR0)
    sei
    push r31
    ldi r31, 0
    subi r30, lo8(-(rx_buf))
    sbci r31, hi8(-(rx_buf))
    st Z, r24
    pop r31
1:  pop r30
    pop r25
    pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti
2:  lds r24, _SFR_MEM_ADDR(UDR0) /* full: read it all the same (clears RXC0), lose it */
    rjmp 1b

/* USART0 data register empty: masks its own interrupt (UDRIE0: it cannot nest in itself) and
 * re-enables interrupts 19 cycles after the vector, then sends tx_buf[tx_tail] (256 bytes, the
 * index wraps as a byte) and unmasks itself if there was one; an empty ring leaves it masked until
 * hal_tx adds a byte. UCSR0B is written by no other handler (hal_tx's read-modify-write in the main
 * loop cannot come between this one's), so the unmasking needs no cli. */
    .global USART0_UDRE_vect
USART0_UDRE_vect:
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    lds r24, _SFR_MEM_ADDR(UCSR0B)
    andi r24, ~_BV(UDRIE0)
    sts _SFR_MEM_ADDR(UCSR0B), r24
    sei
    push r25
    push r30
    push r31
    lds r30, tx_tail
    lds r25, tx_head
    cp r30, r25
    breq 1f /* empty: stays masked */
    mov r25, r30
    inc r25
    ldi r31, 0
    subi r30, lo8(-(tx_buf))
    sbci r31, hi8(-(tx_buf))
    ld r24, Z
    sts _SFR_MEM_ADDR(UDR0), r24
    sts tx_tail, r25
    lds r24, _SFR_MEM_ADDR(UCSR0B)
    ori r24, _BV(UDRIE0)
    sts _SFR_MEM_ADDR(UCSR0B), r24
1:  pop r31
    pop r30
    pop r25
    pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti
