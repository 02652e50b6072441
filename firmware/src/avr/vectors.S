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

/* The clock's overflow flag register, as board.c's CLOCK_TIFR (the plant image's is timer 4's). */
#ifdef USMSWITCH_PLANT_STAMP_ERROR
#define CUT_TCNTL TCNT4L
#define CUT_TCNTH TCNT4H
#define CUT_TIFR TIFR4
#else
#define CUT_TCNTL TCNT5L
#define CUT_TCNTH TCNT5H
#define CUT_TIFR TIFR5
#endif

/* The cut's record for the main loop (cut_flag = r24's value on entry): the counter, the clock's
 * low byte and its overflow flag; then disarmed (stop_mask, drive_on). Uses r24; no SREG change. */
.macro CUT_RECORD
    sts cut_flag, r24
    lds r24, _SFR_MEM_ADDR(CUT_TCNTL)
    sts cut_tick, r24
    lds r24, _SFR_MEM_ADDR(CUT_TCNTH)
    sts cut_tick+1, r24
    lds r24, clock_ovf
    sts cut_ovf, r24
    in r24, _SFR_IO_ADDR(CUT_TIFR)
    sts cut_tifr, r24
    ldi r24, 0
    sts stop_mask, r24
    sts drive_on, r24
.endm


/* The arrival's cut. Each sensor's line is also on an external interrupt pin (A: INT4, PE4, D2;
 * B: INT5, PE5, D3; the wiring is required), falling edge: the sensor goes active. Vectors 5 and 6
 * outrank every other, so only an interrupts-off stretch already running holds one back, never
 * another handler's turn. When the sensor is the armed arrival's (stop_mask) it sets COM4A to
 * "clear" and strobes FOC4A: OC4A is low 19 cycles after the vector (5 to enter, 3 for its jmp,
 * 11 here). Then it leaves the cut's instant for the main loop (cut_flag: 1 A, 2 B; the counter,
 * the clock's low byte and its overflow flag), which ends the stroke as an arrival at that instant
 * should no capture of the edge come (a capture unit out of step with its pin), and disarms
 * itself (stop_mask, drive_on). Not armed, it still cuts when the start's final match has come
 * (OCF4A up, cmp_phase final) for a stroke to this sensor and its handler has not run yet: that
 * handler is outranked by this one, which would otherwise leave the drive on past the arrival
 * until it ran. No instruction here changes SREG, so it is not saved; interrupts stay off
 * throughout. */
.macro ARRIVAL_CUT maskbit, which
    push r24
    lds r24, stop_mask
    sbrs r24, \maskbit
    rjmp 3f
2:  DRIVE_OFF_NOW
    ldi r24, \which
    CUT_RECORD
1:  pop r24
    reti
3:  sbis _SFR_IO_ADDR(TIFR4), OCF4A /* not armed: is the start's match in, its handler not run? */
    rjmp 1b
    lds r24, cmp_phase
    sbrs r24, 1 /* CMP_FINAL: the match that turned the drive on */
    rjmp 1b
    lds r24, dest_mask
    sbrs r24, \maskbit
    rjmp 1b
    rjmp 2b /* the arrival of the stroke whose drive just went on: cut, 33 cycles from the vector */
.endm

    .global INT4_vect
INT4_vect:
    ARRIVAL_CUT 0, 1

    .global INT5_vect
INT5_vect:
    ARRIVAL_CUT 1, 2

/* A capture vector masks its own unit (ICIEn) with interrupts off, turns them on and calls its
 * tail (board.c, a plain C function: the registers a call may change are saved here, r1 cleared),
 * then turns them off again before it unmasks the unit, and returns. The tail therefore never
 * nests in itself (issue 33: the tails of before re-enabled interrupts before their epilogue with
 * the unit armed, and a 40 kHz line nested them until the stack ran through RAM), while an
 * arrival's cut, the UART and the other unit still get in: interrupts are off here for 19 cycles
 * from the vector and 19 to the end of RETI. A unit whose edge found the event ring full stays
 * masked (cap_blanked) until the main loop has emptied it. RAMPZ is saved as avr-gcc's handlers
 * save it. */
.macro CAPTURE_STUB timsk, icie, tail, blankbit
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    lds r24, \timsk
    andi r24, ~_BV(\icie)
    sts \timsk, r24
    sei
    push r0
    push r1
    clr r1
    push r18
    push r19
    push r20
    push r21
    push r22
    push r23
    push r25
    push r26
    push r27
    push r30
    push r31
    in r24, _SFR_IO_ADDR(RAMPZ)
    push r24
    call \tail
    pop r24
    out _SFR_IO_ADDR(RAMPZ), r24
    pop r31
    pop r30
    pop r27
    pop r26
    pop r25
    pop r23
    pop r22
    pop r21
    pop r20
    pop r19
    pop r18
    pop r1
    pop r0
    cli
    lds r24, cap_blanked
    sbrc r24, \blankbit
    rjmp 2f /* blanked (the event ring was full): the main loop unmasks it */
    lds r24, \timsk
    ori r24, _BV(\icie)
    sts \timsk, r24
2:  pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti
.endm

    .global TIMER4_CAPT_vect
TIMER4_CAPT_vect:
    CAPTURE_STUB _SFR_MEM_ADDR(TIMSK4), ICIE4, capture_a_tail, 0

    .global TIMER5_CAPT_vect
TIMER5_CAPT_vect:
    CAPTURE_STUB _SFR_MEM_ADDR(TIMSK5), ICIE5, capture_b_tail, 1

/* The start's compare match (timer 4 compare A), interrupts off throughout. At the final match
 * (cmp_phase 2) the hardware has set OC4A, the drive is on. First a look at the destination
 * sensor, and the drive cut now if the mover is there (an arrival the external interrupt found
 * disarmed): OC4A low 34 cycles from the vector. Else the cut is armed (stop_mask, drive_on) and
 * the sensor looked at once more, for an arrival in between. Then the START is left to the main
 * loop (start_pending 2: the due instant is its stamp): 59 cycles in all without a cut. OCIE4A
 * stays on (a match a period later finds cmp_phase idle and returns; the stroke's end masks it).
 * At the pre-arm match, __vector_compare_rest (board.c) moves OCR4A. */
    .global TIMER4_COMPA_vect
TIMER4_COMPA_vect:
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    lds r24, cmp_phase
    cpi r24, 2 /* CMP_FINAL */
    breq 5f
    rjmp 3f /* the pre-arm match */
5:  push r25
    lds r24, dest_mask
    lds r25, _SFR_MEM_ADDR(PINL)
    and r25, r24 /* the destination's line: low when the mover is there */
    brne 1f
    DRIVE_OFF_NOW /* 34 cycles from the vector */
    lds r24, dest_mask
    CUT_RECORD /* stop_mask and drive_on stay 0 */
    rjmp 4f
1:  lds r25, cut_flag
    tst r25
    brne 4f /* the external interrupt has cut it already (its window path): leave it disarmed */
    sts stop_mask, r24 /* armed: the external interrupt cuts from here on */
    ldi r25, 1
    sts drive_on, r25
    lds r25, _SFR_MEM_ADDR(PINL) /* and a look again, for an arrival in between */
    and r25, r24
    brne 4f
    DRIVE_OFF_NOW
    lds r24, dest_mask
    CUT_RECORD
4:  ldi r24, 0 /* CMP_IDLE */
    sts cmp_phase, r24
    ldi r24, 2
    sts start_pending, r24
    pop r25
    pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti
3:  pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    jmp __vector_compare_rest

/* USART0 receive: masks its own interrupt (RXCIE0) with interrupts off, turns them on, reads the
 * byte (which clears RXC0) into the 128-byte ring, and turns them off again before it unmasks
 * itself and returns: it never nests in itself (the USART keeps a second byte meanwhile). The
 * main loop, the ring's reader, runs only when every handler has returned. A full ring loses the
 * byte; its frame then fails COBS or CRC and is counted. */
    .global USART0_RX_vect
USART0_RX_vect:
    push r24
    in r24, _SFR_IO_ADDR(SREG)
    push r24
    lds r24, _SFR_MEM_ADDR(UCSR0B)
    andi r24, ~_BV(RXCIE0)
    sts _SFR_MEM_ADDR(UCSR0B), r24
    sei
    push r25
    push r30
    push r31
    lds r30, rx_head
    mov r25, r30
    inc r25
    andi r25, 0x7F /* RXQ = 128 */
    lds r24, _SFR_MEM_ADDR(UDR0)
    lds r31, rx_tail
    cp r25, r31
    breq 1f /* full: the byte is lost */
    ldi r31, 0
    subi r30, lo8(-(rx_buf))
    sbci r31, hi8(-(rx_buf))
    st Z, r24
    sts rx_head, r25
1:  pop r31
    pop r30
    pop r25
    cli
    lds r24, _SFR_MEM_ADDR(UCSR0B)
    ori r24, _BV(RXCIE0)
    sts _SFR_MEM_ADDR(UCSR0B), r24
    pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti

/* USART0 data register empty: masks its own interrupt (UDRIE0), turns interrupts on, sends
 * tx_buf[tx_tail] (256 bytes, the index wraps as a byte), and with interrupts off again unmasks
 * itself if there was one; an empty ring leaves it masked until hal_tx adds a byte (hal_tx
 * unmasks it with interrupts off, and runs only when no handler does). */
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
    pop r31
    pop r30
    pop r25
    cli
    lds r24, _SFR_MEM_ADDR(UCSR0B)
    ori r24, _BV(UDRIE0)
    sts _SFR_MEM_ADDR(UCSR0B), r24
    rjmp 2f
1:  pop r31
    pop r30
    pop r25
    cli
2:  pop r24
    out _SFR_IO_ADDR(SREG), r24
    pop r24
    reti

/* Any interrupt without a handler of its own (avr-libc's __bad_interrupt jumps here; its default
 * jumps to 0, a restart with no reset that leaves the I/O as it was): the drive off, and wait with
 * interrupts off for the watchdog, whose reset then says why (BOOT, reset cause WATCHDOG). */
    .global __vector_default
__vector_default:
    DRIVE_OFF_NOW
1:  rjmp 1b
