/* usmswitch-avrsim: the usmswitch firmware in simavr, its UART on a pty, its sensors driven by
 * the project's rig model (firmware/harness/rig_helper.py, a child process on a pipe).
 *
 *   usmswitch-avrsim --elf ELF --link PATH [--truth CSV] [--seed N] [--ppm N]
 *                    [--clock-start-us N] [--start-at A|B] [--python PY] [--helper SCRIPT]
 *                    [--rt-priority N]
 *   usmswitch-avrsim --elf ELF --lockstep [...]     UART over stdin/stdout, time on command
 *
 * Real time (--link): emulated time is paced to the wall clock (scaled by --ppm, the crystal's
 * error); the UART is bridged to a pty whose slave gets a symlink at PATH. The emulated board is
 * hardware of its own, not one more process of the host under test: where allowed it runs at
 * SCHED_FIFO --rt-priority (default 60, above a daemon's loop at 50; 0: do not ask), else at
 * nice -10, so that the host's load cannot make emulated time fall behind the wall clock.
 * Lockstep: as fast as the CPU goes, time advancing only on command; the UART's bytes are
 * exchanged on stdin/stdout. Commands on stdin (both modes, one a line):
 *   send HEX     bytes to the firmware's UART (lockstep)
 *   run US       run US microseconds of emulated time, print "uart HEX" (lockstep) and "ran CYCLE"
 *   runto CYCLE  the same, to an emulator cycle     edge CH LEVEL CYCLE  a sensor line at a cycle
 *   trace N      what to print as it happens (1-3)  stats   the measurements   info   the origin
 *   statsreset   the longest watchdog-kick interval and the lowest stack pointer measured from now
 *   wire CH 0|1  sensor CH's line cut from its capture pin (a broken wire) or joined again
 *   badirq       an interrupt the firmware has no handler for (INT0, enabled behind its back)
 *   square CH FIRST HALF COUNT   line noise: COUNT toggles of a sensor's line over the rig's
 *                level, HALF cycles apart, from cycle FIRST (a square wave picked up from the drive)
 *   stall        the next stroke jams half way       bounce   the next arrival bounces
 *   unplug       close the pty, remove the symlink   replug   new pty (and a power-on reset)
 *   quit
 * --truth CSV gets a row per stroke: stroke,direction,start_us,depart_us,arrive_us,off_us,
 * cut_ns (arrival edge to drive off), on the firmware's microsecond clock, from emulator cycles.
 *
 * simavr 1.6 (Debian bookworm) gets these corrections here, none in the firmware (--emulator-bugs
 * leaves them out, for the test that shows each one):
 *  1. a write to TIFRn cleared every pending flag of the timer, not only the bits written as 1;
 *  2. SEI and RETI enabled interrupts two instructions late instead of one;
 *  3. FOCnx (force output compare) was ignored;
 *  4. in normal mode the OCnx pin was set or cleared at every overflow as in PWM modes: the
 *     drive pin here is the harness's own model of the OC4A latch and the COM4A mux;
 *  5. GTCCR's TSM (prescaler halt) was ignored: timers zeroed one instruction apart while the
 *     prescaler was halted counted a few cycles apart, so ICR5 stamps were a tick behind ICR4's
 *     (1 us off in one edge of six); when the firmware releases TSM the harness restarts timers 4
 *     and 5 from the values written to them meanwhile, as the chip starts them together;
 *  (and the sensor pins are driven as the port's external state: simavr let the internal pull-up
 *  override a line the sensor pulls low; each sensor line drives its capture pin on port L and
 *  its external interrupt pin on port E, as docs/firmware.md wires it);
 *  7. an interrupt was entered in no cycles (the chip: 5, and 14 from sleep), added here;
 *  8. a power-on ("replug") left MCUSR clear (the chip sets PORF);
 *  9. a low external interrupt pin whose ISCn bits are 00 (the reset value: a level interrupt)
 *     made simavr poll that pin every cycle, enabled in EIMSK or not, and set its INTFn (the chip
 *     sets no flag for a level interrupt, and a disabled one does nothing). The firmware's unused
 *     INTn pins float low, so those polls took 90 % of the harness's CPU and left emulated time
 *     barely ahead of the wall clock (4 s emulated in 3.4 s; 0.2 s without): the harness turns
 *     simavr's level polling off, and stops, naming the pin, if the firmware ever enables an INTn
 *     in level mode, which it would then no longer emulate as the chip does.
 * It also follows the chip's resets (the watchdog's: the drive pin, the clock's origin) and
 * measures what the firmware does with interrupts off and how often the main loop kicks the
 * watchdog ("stats"; lockstep "trace N" for the details, docs/firmware.md).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <gelf.h>
#include <libelf.h>
#include <math.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_timer.h"
#include "avr_uart.h"
#include "avr_watchdog.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_interrupts.h"
#include "sim_io.h"

#define F_CPU 16000000.0
/* ATmega2560 data addresses */
#define A_PORTH 0x102
#define A_TCCR4A 0xA0
#define A_TCCR4C 0xA2
#define A_TCNT4L 0xA4
#define A_TCNT5L 0x124
#define A_GTCCR 0x43
#define A_MCUSR 0x54
#define MCUSR_PORF 0x01
#define MCUSR_WDRF 0x08
/* The vector table: 57 vectors of 4 bytes (jmp); a capture vector address is its number times 4. */
#define VECTORS_END (57 * 4)
#define VEC_CAPT4 41
#define VEC_CAPT5 46
#define OP_WDR 0x95A8
#define BIT_FOC4A 7
/* Real time: the longest sleep once emulated time has caught up with the wall clock. */
#define IDLE_NS 500000

static avr_t *avr;
static int fix_bugs = 1;
static int lockstep;
static double ppm;
static int rt_priority = 60;
static uint32_t clock_start_us;
static uint16_t clock_ovf_addr;
static avr_cycle_count_t origin_cycle; /* cycle of the firmware's TCNT4 = 0 */
static avr_cycle_count_t max_lag, max_lag_at; /* the worst lag behind the wall clock, and when */
static double max_unread_s; /* the longest the pty went unread while the chip ran (wall time) */
static int origin_set;

/* ---- what the harness measures of the firmware ("stats", and at exit on stderr) ----
 * Every stretch with interrupts off (SREG.I = 0), keyed by where it began: the instruction after
 * the CLI (or the write to SREG) that cleared the flag, or the vector an interrupt entered by.
 * Its length runs from the cycle the flag went to 0 to the cycle it is 1 again (one instruction
 * more then runs before a pending interrupt is taken, as on the chip). Also the longest time
 * between two WDR instructions (the main loop's watchdog kicks) and the watchdog resets. */
#define MAX_SPANS 160
struct span {
    uint32_t pc;
    unsigned long long count;
    avr_cycle_count_t max, max_at;
};
static struct span spans[MAX_SPANS];
static int nspans;
static int i_prev = 1;
static avr_cycle_count_t span_start;
static uint32_t span_pc;
static avr_cycle_count_t wdr_last, wdr_max, wdr_max_at;
static unsigned long long wdr_count;
static unsigned long resets_wdt;
/* The lowest the stack pointer went (stats "sp MIN AT"): a stack that grew into .bss shows here. */
static uint16_t sp_min = 0xFFFF;
static avr_cycle_count_t sp_min_at;
static int reset_seen;
/* lockstep "trace N": 1 prints "irq VECTOR CYCLE" as each interrupt is entered and "sensor CH
 * LEVEL CYCLE FW_US SPAN" as each sensor edge comes (SPAN: where the interrupts-off span then in
 * progress began, -1 if none); 2 also "cli WHERE PC START CYCLES" as each span ends. */
static int trace_irqs;
static avr_watchdog_t *wdt;
static void (*core_reset)(avr_t *);

static void die(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fprintf(stderr, "usmswitch-avrsim: ");
    vfprintf(stderr, fmt, ap);
    fprintf(stderr, "\n");
    va_end(ap);
    exit(2);
}

/* ---- time ---- */
static double f_eff(void) { return F_CPU * (1.0 + ppm * 1e-6); } /* the crystal's real rate */

static uint64_t cycles_to_ns(avr_cycle_count_t c) { return (uint64_t)((double)c * 1e9 / f_eff()); }

static avr_cycle_count_t ns_to_cycles(uint64_t ns) { return (avr_cycle_count_t)ceil((double)ns * f_eff() / 1e9); }

/* The firmware's microsecond clock at cycle c: (clock_ovf << 15) + TCNT4 / 2, TCNT4 at clk/8. */
static uint32_t fw_us(avr_cycle_count_t c)
{
    if (!origin_set || c < origin_cycle)
        return 0;
    uint64_t ticks = (c - origin_cycle) / 8;
    return (uint32_t)(((uint64_t)(clock_start_us / 32768u) << 15) + ticks / 2);
}

/* ---- the rig helper ---- */
static FILE *helper_in, *helper_out;
static pid_t helper_pid;

struct edge {
    avr_cycle_count_t at;
    int ch, level;
};
#define MAX_EDGES 16
static struct edge pending[MAX_EDGES];
static int npending;
static int sensor_active[2]; /* the rig's level of each sensor (1 active) */
/* Line noise ("square CH FIRST HALF COUNT"): a square wave over the rig's level; the line the
 * firmware sees is the rig's level XOR noise_x. COUNT toggles, HALF cycles apart, from FIRST. */
static int noise_x[2];
static avr_cycle_count_t noise_next[2], noise_half[2];
static unsigned long noise_left[2];
static int line_active(int ch) { return sensor_active[ch] ^ noise_x[ch]; }
/* "wire CH 0": sensor CH's line no longer reaches its capture pin (a broken wire; the pin's pull-up
 * holds it released), only its external interrupt pin. "wire CH 1" joins it again. */
static int capture_wired[2] = {1, 1};
static int capture_active(int ch) { return capture_wired[ch] && line_active(ch); }
static avr_irq_t *sensor_irq[2], *sensor_int_irq[2];

static void helper_start(const char *python, const char *script, int seed, char start_at)
{
    int to_child[2], from_child[2];
    if (pipe(to_child) || pipe(from_child))
        die("pipe: %s", strerror(errno));
    helper_pid = fork();
    if (helper_pid < 0)
        die("fork: %s", strerror(errno));
    if (helper_pid == 0) {
        dup2(to_child[0], 0);
        dup2(from_child[1], 1);
        close(to_child[1]);
        close(from_child[0]);
        char seed_s[32], at_s[2] = {start_at, 0};
        snprintf(seed_s, sizeof seed_s, "%d", seed);
        /* The model's numpy would start a BLAS thread per core that spins after each call:
         * one thread is all it needs, and the rest would take the CPU the emulation paces on. */
        setenv("OPENBLAS_NUM_THREADS", "1", 1);
        setenv("OMP_NUM_THREADS", "1", 1);
        execlp(python, python, script, "--seed", seed_s, "--start-at", at_s, (char *)NULL);
        fprintf(stderr, "usmswitch-avrsim: exec %s: %s\n", python, strerror(errno));
        _exit(127);
    }
    close(to_child[0]);
    close(from_child[1]);
    helper_in = fdopen(to_child[1], "w");
    helper_out = fdopen(from_child[0], "r");
}

static int edges_changed;

static avr_cycle_count_t edge_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    return 0; /* only a bound for the sleep */
}

static void add_edge(avr_cycle_count_t at, int ch, int level)
{
    if (npending >= MAX_EDGES)
        die("too many pending sensor edges");
    /* The edge may come while simavr is inside a step (the drive went on at a compare match):
     * a sleeping core would then skip to its next timer, past the edge. This timer stops it at the
     * edge; run_until applies the edge there. */
    avr_cycle_timer_register(avr, at > avr->cycle ? at - avr->cycle : 1, edge_timer, &pending[npending]);
    pending[npending++] = (struct edge){at, ch, level};
    edges_changed = 1;
}

/* Send a request, read "edge" lines until "end" (or the "sensors" answer to init). */
static void helper_ask(const char *fmt, ...)
{
    char line[256];
    va_list ap;
    va_start(ap, fmt);
    vfprintf(helper_in, fmt, ap);
    va_end(ap);
    fputc('\n', helper_in);
    fflush(helper_in);
    for (;;) {
        if (!fgets(line, sizeof line, helper_out))
            die("rig helper exited");
        unsigned long long t;
        int ch, level, a, b;
        if (sscanf(line, "edge %llu %d %d", &t, &ch, &level) == 3)
            add_edge(ns_to_cycles(t), ch, level);
        else if (sscanf(line, "sensors %d %d", &a, &b) == 2) {
            sensor_active[0] = a;
            sensor_active[1] = b;
            return;
        } else if (strncmp(line, "end", 3) == 0)
            return;
        else
            die("rig helper said: %s", line);
    }
}

/* ---- truth ---- */
static FILE *truth;
static int stroke_no;
static struct {
    int on, direction, departed, arrived;
    avr_cycle_count_t start, depart, arrive;
} cur;

/* Drive the sensor lines (active low). Also as the port's "external" state: simavr 1.6 lets the
 * internal pull-up (PORTL = 1 on an input) override a line the sensor pulls low; a real pin
 * follows the stronger external driver. */
static void drive_sensor_pins(void)
{
    avr_ioport_external_t ext = {.name = 'L', .mask = 3, .value = 0};
    ext.value = (unsigned)((capture_active(0) ? 0 : 1) | (capture_active(1) ? 0 : 2));
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('L'), &ext);
    /* Each sensor's line is wired to a second pin too (docs/firmware.md): A to PE4 (INT4), B to PE5. */
    avr_ioport_external_t ext_e = {.name = 'E', .mask = 0x30, .value = 0};
    ext_e.value = (unsigned)((line_active(0) ? 0 : 0x10) | (line_active(1) ? 0 : 0x20));
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('E'), &ext_e);
    for (int ch = 0; ch < 2; ch++) {
        avr_raise_irq(sensor_irq[ch], capture_active(ch) ? 0 : 1);
        avr_raise_irq(sensor_int_irq[ch], line_active(ch) ? 0 : 1);
    }
}

/* The rig moves a sensor (noise 0) or the noise toggles it (noise 1); the line is what counts. */
static void line_change(int ch, int active, int noise)
{
    int before = line_active(ch);
    if (noise)
        noise_x[ch] ^= 1;
    else
        sensor_active[ch] = active;
    drive_sensor_pins();
    int line = line_active(ch);
    if (line == before)
        return;
    if (lockstep && trace_irqs) /* the edge's truth, and what held interrupts off as it came */
        printf("sensor %d %d %llu %lu %ld\n", ch, line, (unsigned long long)avr->cycle,
               (unsigned long)fw_us(avr->cycle), avr->sreg[S_I] ? -1L : (long)span_pc);
    if (!cur.on)
        return;
    int source = cur.direction == 0 ? 0 : 1;
    if (ch == source && !line && !cur.departed) {
        cur.departed = 1;
        cur.depart = avr->cycle;
    }
    if (ch == (source ^ 1) && line && !cur.arrived) {
        cur.arrived = 1;
        cur.arrive = avr->cycle;
    }
}

static void set_sensor(int ch, int active) { line_change(ch, active, 0); }

/* ---- the drive pin: OC4A latch and COM4A mux, modelled here (simavr's is wrong) ---- */
static int oc4a_latch, drive_pin;
static avr_timer_t *timer4, *timer5;

static void drive_update(void)
{
    uint8_t com = (avr->data[A_TCCR4A] >> 6) & 3;
    int pin = com ? oc4a_latch : (avr->data[A_PORTH] >> 3) & 1;
    if (pin == drive_pin)
        return;
    drive_pin = pin;
    avr_cycle_count_t c = avr->cycle;
    if (lockstep)
        printf("drive %d %llu %lu\n", pin, (unsigned long long)c, (unsigned long)fw_us(c));
    if (pin) {
        cur.on = 1;
        cur.direction = (avr->data[A_PORTH] >> 4) & 1;
        cur.departed = cur.arrived = 0;
        cur.start = c;
        stroke_no++;
        npending = 0;
        helper_ask("on %llu %d", (unsigned long long)cycles_to_ns(c), cur.direction);
        /* Already at the destination: the far sensor is active as the drive goes on. */
        if (line_active(cur.direction == 0 ? 1 : 0) && !cur.arrived) {
            cur.arrived = 1;
            cur.arrive = c;
        }
    } else {
        /* Edges not yet due end here; the helper may send bounce edges. */
        int keep = 0;
        for (int i = 0; i < npending; i++)
            if (pending[i].at <= c)
                pending[keep++] = pending[i];
        npending = keep;
        helper_ask("off %llu", (unsigned long long)cycles_to_ns(c));
        if (truth && cur.on) {
            fprintf(truth, "%d,%d,%lu,", stroke_no, cur.direction, (unsigned long)fw_us(cur.start));
            if (cur.departed)
                fprintf(truth, "%lu", (unsigned long)fw_us(cur.depart));
            fputc(',', truth);
            if (cur.arrived)
                fprintf(truth, "%lu", (unsigned long)fw_us(cur.arrive));
            fprintf(truth, ",%lu,", (unsigned long)fw_us(c));
            if (cur.arrived)
                fprintf(truth, "%.0f", (double)(c - cur.arrive) * 1e9 / F_CPU);
            fputc('\n', truth);
            fflush(truth);
        }
        cur.on = 0;
    }
}

static void apply_com(uint8_t com)
{
    if (com == 1)
        oc4a_latch ^= 1;
    else if (com == 2)
        oc4a_latch = 0;
    else if (com == 3)
        oc4a_latch = 1;
}

/* Compare match A of timer 4 (the interrupt flag rises): the hardware's pin action. */
static void on_compa(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (!value)
        return;
    apply_com((avr->data[A_TCCR4A] >> 6) & 3);
    drive_update();
}

static void w_tccr4c(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)addr;
    (void)param;
    if (fix_bugs && (v & (1 << BIT_FOC4A))) /* FOC bits read as zero: nothing stored */
        apply_com((avr->data[A_TCCR4A] >> 6) & 3);
    drive_update();
}

static void w_watch(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)addr;
    (void)v;
    (void)param;
    drive_update(); /* simavr's own handler has stored the value */
}

/* Correction 5: TSM. While GTCCR.TSM holds the prescaler, a counter written keeps its value;
 * simavr counts on. The values written to TCNT4 and TCNT5 meanwhile are kept here, and both
 * counters restart from them, through simavr's own write handlers, when TSM is released. */
static int tsm_on;
static int tcnt_held[2];
static uint16_t tcnt_written[2];

static void hold_tcnt(int i, avr_io_addr_t addr, uint8_t v)
{
    if (tsm_on) {
        tcnt_held[i] = 1;
        tcnt_written[i] = (uint16_t)(v | (avr->data[addr + 1] << 8));
    }
}

/* The firmware zeroes TCNT4 (its clock's origin) and releases the prescaler: the origin is where
 * timer 4 starts counting from zero. */
static void w_tcnt4l(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)param;
    hold_tcnt(0, addr, v);
    if (v == 0 && avr->data[A_TCNT4L + 1] == 0) {
        origin_cycle = avr->cycle;
        origin_set = 1;
    }
}

static void w_tcnt5l(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)param;
    hold_tcnt(1, addr, v);
}

static void restart_tcnt(void)
{
    static const avr_io_addr_t lo[2] = {A_TCNT4L, A_TCNT5L};
    for (int i = 1; i >= 0; i--) { /* timer 4 last: its handler sets the origin here */
        if (!tcnt_held[i])
            continue;
        tcnt_held[i] = 0;
        avr_io_addr_t io = AVR_DATA_TO_IO(lo[i]);
        avr->data[lo[i] + 1] = (uint8_t)(tcnt_written[i] >> 8);
        avr->io[io].w.c(avr, lo[i], (uint8_t)tcnt_written[i], avr->io[io].w.param);
    }
}

static void w_gtccr(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)param;
    avr->data[addr] = v;
    int released = tsm_on && !(v & 0x80);
    tsm_on = fix_bugs && (v & 0x80);
    if (released)
        restart_tcnt();
    if (!(v & 0x80) && clock_ovf_addr) { /* TSM released: the clock starts; preset its high part */
        uint32_t ovf = clock_start_us / 32768u;
        for (int i = 0; i < 4; i++)
            avr->data[clock_ovf_addr + i] = (uint8_t)(ovf >> (8 * i));
    }
}

/* Any reset of the chip (the watchdog's, or "replug"): the I/O registers are cleared, so the drive
 * pin is PORTH's (low); the harness's models of the OC4A latch and of TSM start over, and the clock
 * has no origin until the firmware zeroes TCNT4 again. RAM is kept, as on the chip. */
static void on_reset(avr_t *a)
{
    if (core_reset)
        core_reset(a);
    int by_wdt = wdt && wdt->reset_context.wdrf; /* simavr sets WDRF after this, in its port reset */
    avr_cycle_count_t c = avr->cycle;
    if (by_wdt) {
        resets_wdt++;
        if (lockstep)
            printf("reset watchdog %llu %lu\n", (unsigned long long)c, (unsigned long)fw_us(c));
        else
            fprintf(stderr, "usmswitch-avrsim: watchdog reset at %.6f s\n", (double)c / f_eff());
    }
    oc4a_latch = 0;
    tsm_on = tcnt_held[0] = tcnt_held[1] = 0;
    drive_update();
    origin_set = 0;
    reset_seen = 1;
    wdr_last = 0;
}

/* Correction 1: clear only the TIFR bits written as one. */
static void clear_if(avr_int_vector_t *vec, avr_io_addr_t addr, uint8_t v)
{
    if (vec->raised.reg == addr && (v & (1 << vec->raised.bit)) && avr_regbit_get(avr, vec->raised))
        avr_clear_interrupt(avr, vec);
}

static void w_tifr_fixed(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    avr_timer_t *t = param;
    clear_if(&t->overflow, addr, v);
    clear_if(&t->icr, addr, v);
    for (int i = 0; i < AVR_TIMER_COMP_COUNT; i++)
        clear_if(&t->comp[i].interrupt, addr, v);
}

/* Correction 10: an interrupt whose enable bit is written to 1 while its flag is already up is
 * taken on the chip (the flag is the request); simavr 1.6 queues an interrupt only as its flag
 * rises with the enable bit set, so one masked meanwhile was lost (a capture unit that masks
 * itself while its handler runs never saw the edge that came then). After a write to an enable
 * register, each of its vectors whose enable bit and flag are both set is raised again. */
#define MAX_REENABLE 12
static avr_int_vector_t *reenable_vec[MAX_REENABLE];
static int nreenable;
struct chained_write {
    avr_io_addr_t addr;
    avr_io_write_t c;
    void *param;
};
static struct chained_write reenable_w[4];
static int nreenable_w;

static void w_enable(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    for (int i = 0; i < nreenable_w; i++)
        if (reenable_w[i].addr == addr) {
            if (reenable_w[i].c)
                reenable_w[i].c(a, addr, v, reenable_w[i].param);
            else
                avr->data[addr] = v;
        }
    for (int i = 0; i < nreenable; i++) {
        avr_int_vector_t *vec = reenable_vec[i];
        if (vec->enable.reg == addr && avr_regbit_get(avr, vec->enable) && vec->raised.reg &&
            avr_regbit_get(avr, vec->raised) && !avr_is_interrupt_pending(avr, vec))
            avr_raise_interrupt(avr, vec);
    }
}

static void reenable_watch(avr_int_vector_t *vec)
{
    if (nreenable == MAX_REENABLE)
        die("correction 10: too many vectors");
    reenable_vec[nreenable++] = vec;
    avr_io_addr_t addr = vec->enable.reg;
    for (int i = 0; i < nreenable_w; i++)
        if (reenable_w[i].addr == addr)
            return;
    avr_io_addr_t io = AVR_DATA_TO_IO(addr);
    reenable_w[nreenable_w++] = (struct chained_write){addr, avr->io[io].w.c, avr->io[io].w.param};
    avr->io[io].w.c = w_enable;
    avr->io[io].w.param = NULL;
}

static avr_timer_t *find_timer(char name)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (io->kind && !strcmp(io->kind, "timer") && ((avr_timer_t *)io)->name == name)
            return (avr_timer_t *)io;
    die("no timer %c in this core", name);
    return NULL;
}

static void fix_tifr(avr_timer_t *t)
{
    avr_io_addr_t a = AVR_DATA_TO_IO(t->overflow.raised.reg);
    if (avr->io[a].w.param != t)
        die("timer %c: TIFR write handler is not simavr's own (shared register?)", t->name);
    avr->io[a].w.c = w_tifr_fixed;
}

/* ---- ELF symbols: clock_ovf's address, and the functions (to name interrupts-off spans) ---- */
#define MAX_FUNCS 512
static struct func {
    uint32_t addr, size;
    char name[48];
} funcs[MAX_FUNCS];
static int nfuncs;

static uint16_t elf_symbol(const char *path, const char *name)
{
    if (elf_version(EV_CURRENT) == EV_NONE)
        die("libelf: %s", elf_errmsg(-1));
    int fd = open(path, O_RDONLY);
    if (fd < 0)
        die("%s: %s", path, strerror(errno));
    Elf *e = elf_begin(fd, ELF_C_READ, NULL);
    Elf_Scn *scn = NULL;
    uint16_t addr = 0;
    while ((scn = elf_nextscn(e, scn))) {
        GElf_Shdr sh;
        gelf_getshdr(scn, &sh);
        if (sh.sh_type != SHT_SYMTAB)
            continue;
        Elf_Data *d = elf_getdata(scn, NULL);
        for (size_t i = 0; i < sh.sh_size / sh.sh_entsize; i++) {
            GElf_Sym s;
            gelf_getsym(d, (int)i, &s);
            const char *sname = elf_strptr(e, sh.sh_link, s.st_name);
            if (!strcmp(sname, name))
                addr = (uint16_t)(s.st_value & 0xFFFF); /* data addresses carry 0x800000 */
            if (GELF_ST_TYPE(s.st_info) == STT_FUNC && s.st_size && nfuncs < MAX_FUNCS) {
                funcs[nfuncs].addr = (uint32_t)s.st_value;
                funcs[nfuncs].size = (uint32_t)s.st_size;
                snprintf(funcs[nfuncs].name, sizeof funcs[nfuncs].name, "%s", sname);
                nfuncs++;
            }
        }
    }
    elf_end(e);
    close(fd);
    return addr;
}

/* "function+0xOFF" for a code byte address (or the vector table, or "reset"). */
static const char *where(uint32_t pc, char *buf, size_t n)
{
    if (pc == 0) {
        snprintf(buf, n, "reset");
        return buf;
    }
    if (pc < VECTORS_END) {
        snprintf(buf, n, "vector%u", pc / 4);
        return buf;
    }
    for (int i = 0; i < nfuncs; i++)
        if (pc >= funcs[i].addr && pc < funcs[i].addr + funcs[i].size) {
            snprintf(buf, n, "%s+0x%x", funcs[i].name, pc - funcs[i].addr);
            return buf;
        }
    snprintf(buf, n, "0x%x", pc);
    return buf;
}

static void span_record(uint32_t pc, avr_cycle_count_t len, avr_cycle_count_t at)
{
    int i;
    for (i = 0; i < nspans && spans[i].pc != pc; i++)
        ;
    if (i == nspans) {
        if (nspans == MAX_SPANS)
            return;
        spans[nspans++] = (struct span){.pc = pc};
    }
    spans[i].count++;
    if (len > spans[i].max) {
        spans[i].max = len;
        spans[i].max_at = at;
    }
}

static void print_stats(FILE *f, const char *prefix)
{
    char buf[80];
    for (int i = 0; i < nspans; i++)
        fprintf(f, "%sspan %s 0x%x %llu %llu %llu\n", prefix, where(spans[i].pc, buf, sizeof buf), spans[i].pc,
                spans[i].count, (unsigned long long)spans[i].max, (unsigned long long)spans[i].max_at);
    fprintf(f, "%swdr %llu %llu %llu\n", prefix, wdr_count, (unsigned long long)wdr_max,
            (unsigned long long)wdr_max_at);
    fprintf(f, "%sresets %lu\n", prefix, resets_wdt);
    fprintf(f, "%ssp %u %llu\n", prefix, sp_min, (unsigned long long)sp_min_at);
}

/* ---- UART ---- */
static avr_irq_t *uart_irq;
static uint8_t to_avr[65536];
static size_t to_avr_head, to_avr_len;
static int xon;
static uint8_t from_avr[65536];
static size_t from_avr_len;
static unsigned long dropped_bytes; /* the firmware's bytes the pty would not take, or past the buffer */

/* Each host byte reaches the chip no earlier than the emulated instant it was sent at: a byte
 * read from the pty while the chip is behind the wall clock waits for the chip to get there, as
 * a byte on a wire waits for nothing but arrives when it was sent. Read early, its answer (a
 * PONG, a START) would carry a stamp from before the question, a clock no crystal has, which a
 * host that checks its device's clock rejects (issue 29). */
static avr_cycle_count_t to_avr_at[65536];

static void feed_uart(void);

static avr_cycle_count_t feed_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    feed_uart();
    return 0;
}

static void feed_uart(void)
{
    while (xon && to_avr_len) {
        avr_cycle_count_t at = to_avr_at[to_avr_head];
        if (at > avr->cycle) {
            avr_cycle_timer_cancel(avr, feed_timer, NULL);
            avr_cycle_timer_register(avr, at - avr->cycle, feed_timer, NULL);
            return;
        }
        uint8_t b = to_avr[to_avr_head];
        to_avr_head = (to_avr_head + 1) % sizeof to_avr;
        to_avr_len--;
        avr_raise_irq(uart_irq + UART_IRQ_INPUT, b);
    }
}

/* `at`: the emulated cycle the bytes were sent at (now, for bytes of a lockstep command). */
static void queue_to_avr(const uint8_t *b, size_t n, avr_cycle_count_t at)
{
    for (size_t i = 0; i < n && to_avr_len < sizeof to_avr; i++) {
        size_t slot = (to_avr_head + to_avr_len) % sizeof to_avr;
        to_avr[slot] = b[i];
        to_avr_at[slot] = at;
        to_avr_len++;
    }
    feed_uart();
}

static void on_uart_out(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (from_avr_len < sizeof from_avr)
        from_avr[from_avr_len++] = (uint8_t)value;
    else
        dropped_bytes++; /* 650 ms of output at 1 Mbaud not yet written: reported at the end */
}

static void on_xon(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value) {
        xon = 1;
        feed_uart();
    }
}

static void on_xoff(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value)
        xon = 0;
}

/* Lockstep "trace 3": every byte the firmware reads from UDR0, as it reads it. */
#define A_UDR0 0xC6
static avr_io_read_t udr0_read;
static void *udr0_read_param;

static uint8_t r_udr0(avr_t *a, avr_io_addr_t addr, void *param)
{
    (void)param;
    uint8_t v = udr0_read(a, addr, udr0_read_param);
    if (lockstep && trace_irqs > 2)
        printf("rx %02x %llu\n", v, (unsigned long long)avr->cycle);
    return v;
}

/* ---- pty ---- */
static int pty_master = -1, pty_slave = -1;
/* The pacing: emulated cycle pace_c0 is wall time pace_w0 (set when the pty run starts). */
static double pace_w0;
static avr_cycle_count_t pace_c0;
static double wall_s(void);

/* The emulated cycle the wall clock is at now. */
static avr_cycle_count_t wall_cycle(void)
{
    return pace_c0 + (avr_cycle_count_t)((wall_s() - pace_w0) * f_eff());
}
static char link_path[1024];

static void pty_plug(void)
{
    pty_master = posix_openpt(O_RDWR | O_NOCTTY);
    if (pty_master < 0 || grantpt(pty_master) || unlockpt(pty_master))
        die("pty: %s", strerror(errno));
    struct termios tio;
    tcgetattr(pty_master, &tio);
    cfmakeraw(&tio);
    tcsetattr(pty_master, TCSANOW, &tio);
    fcntl(pty_master, F_SETFL, O_NONBLOCK);
    const char *slave = ptsname(pty_master);
    /* The slave raw too: the host may not set it up before the first bytes. The harness keeps
     * it open: a master whose slave nobody holds polls as hung up (POLLHUP) for ever, which
     * would turn the idle sleep into a spin while no host is attached. */
    pty_slave = open(slave, O_RDWR | O_NOCTTY);
    if (pty_slave < 0)
        die("%s: %s", slave, strerror(errno));
    tcgetattr(pty_slave, &tio);
    cfmakeraw(&tio);
    tcsetattr(pty_slave, TCSANOW, &tio);
    char tmp[1100];
    snprintf(tmp, sizeof tmp, "%s.new", link_path);
    unlink(tmp);
    if (symlink(slave, tmp) || rename(tmp, link_path))
        die("symlink %s: %s", link_path, strerror(errno));
    printf("avrsim on %s via %s\n", slave, link_path);
    fflush(stdout);
}

static void pty_unplug(void)
{
    if (pty_master >= 0)
        close(pty_master);
    if (pty_slave >= 0)
        close(pty_slave);
    pty_master = pty_slave = -1;
    unlink(link_path);
    to_avr_len = 0;
}

/* Behind the wall clock by more than this (200 us of emulated time), the harness catches up in
 * chunks this long, looking at the pty once every CATCH_UP_LOOK_S of wall time. */
#define CATCH_UP_CYCLES 3200
#define CATCH_UP_LOOK_S 0.001

/* How far behind the wall clock the chip is, at worst (printed at the end). */
static void note_lag(avr_cycle_count_t target)
{
    if (target > avr->cycle && target - avr->cycle > max_lag) {
        max_lag = target - avr->cycle;
        max_lag_at = avr->cycle;
    }
}

static void pty_io(void)
{
    if (pty_master < 0) {
        from_avr_len = 0;
        return;
    }
    uint8_t buf[4096];
    ssize_t n;
    while ((n = read(pty_master, buf, sizeof buf)) > 0)
        queue_to_avr(buf, (size_t)n, wall_cycle());
    size_t off = 0;
    while (off < from_avr_len) {
        n = write(pty_master, from_avr + off, from_avr_len - off);
        if (n <= 0) {
            dropped_bytes += from_avr_len - off;
            break; /* nobody reading (EAGAIN) or hung up: the bytes are lost, as on a wire */
        }
        off += (size_t)n;
    }
    from_avr_len = 0;
}

/* ---- running ---- */
static avr_cycle_count_t stop_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    return 0; /* only a bound for the sleep */
}

/* simavr's own sleep callback sleeps in wall time; pacing is this program's job. */
static void no_sleep(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    (void)how_long;
}

/* After each avr_run: the interrupts-off spans, the watchdog kicks, and correction 7: simavr
 * enters an interrupt in no time; the chip takes 5 cycles to push the 3-byte PC and fetch the
 * vector, 5 more when the interrupt wakes it, and is halted 4 cycles on waking (datasheet 7.8.1
 * and 11.1): 5 or 14 cycles, added here so that latencies are not flattered. */
static void after_step(avr_cycle_count_t c0, uint32_t pc0, int was_sleeping)
{
    int i_now = avr->sreg[S_I];
    uint16_t sp = (uint16_t)(avr->data[R_SPL] | (avr->data[R_SPH] << 8));
    if (sp < sp_min) {
        sp_min = sp;
        sp_min_at = avr->cycle;
    }
    if (reset_seen) {
        reset_seen = 0;
        span_start = avr->cycle;
        span_pc = 0;
        i_prev = i_now;
        return;
    }
    if (!was_sleeping && pc0 + 1 < avr->flashend &&
        (avr->flash[pc0] | (avr->flash[pc0 + 1] << 8)) == OP_WDR) {
        if (wdr_last && c0 - wdr_last > wdr_max) {
            wdr_max = c0 - wdr_last;
            wdr_max_at = c0;
        }
        wdr_last = c0;
        wdr_count++;
    }
    if (i_prev && !i_now) {
        span_start = avr->cycle;
        int entered = avr->pc < VECTORS_END && avr->pc != pc0 + 2;
        span_pc = entered ? avr->pc : pc0 + 2;
        if (entered) {
            if (trace_irqs)
                printf("irq %u %llu\n", avr->pc / 4, (unsigned long long)avr->cycle);
            if (fix_bugs)
                avr->cycle += was_sleeping ? 14 : 5;
        }
    } else if (!i_prev && i_now) {
        span_record(span_pc, avr->cycle - span_start, span_start);
        if (trace_irqs > 1) {
            char buf[80];
            printf("cli %s %u %llu %llu\n", where(span_pc, buf, sizeof buf), span_pc,
                   (unsigned long long)span_start, (unsigned long long)(avr->cycle - span_start));
        }
    }
    i_prev = i_now;
}

/* Correction 9; simavr turns the polling on again at every reset. */
static void level_polling_off(void)
{
    if (fix_bugs)
        for (uint8_t i = 0; i < 8; i++)
            avr_extint_set_strict_lvl_trig(avr, i, 0);
}

/* Correction 9's bound: an INTn enabled in level mode would be emulated as an edge. */
#define A_EIMSK 0x3D
#define A_EICRA 0x69
#define A_EICRB 0x6A
static void check_level_interrupts(void)
{
    if (!fix_bugs)
        return;
    uint8_t eimsk = avr->data[A_EIMSK];
    uint16_t isc = (uint16_t)(avr->data[A_EICRA] | (avr->data[A_EICRB] << 8));
    for (int i = 0; i < 8; i++)
        if (((eimsk >> i) & 1) && ((isc >> (2 * i)) & 3) == 0)
            die("the firmware enabled INT%d as a level interrupt, which this harness emulates as an edge "
                "(correction 9 in harness/avrsim.c): teach the harness level interrupts first",
                i);
}

static void run_until(avr_cycle_count_t end)
{
    while (avr->cycle < end) {
        /* the next sensor edge due */
        int next = -1;
        for (int i = 0; i < npending; i++)
            if (next < 0 || pending[i].at < pending[next].at)
                next = i;
        if (next >= 0 && pending[next].at <= avr->cycle) {
            struct edge e = pending[next];
            pending[next] = pending[--npending];
            set_sensor(e.ch, e.level);
            continue;
        }
        int toggled = 0;
        for (int ch = 0; ch < 2; ch++)
            if (noise_left[ch] && noise_next[ch] <= avr->cycle) {
                noise_left[ch]--;
                noise_next[ch] += noise_half[ch];
                line_change(ch, 0, 1);
                toggled = 1;
            }
        if (toggled)
            continue;
        avr_cycle_count_t stop = end;
        if (next >= 0 && pending[next].at < stop)
            stop = pending[next].at;
        for (int ch = 0; ch < 2; ch++)
            if (noise_left[ch] && noise_next[ch] < stop)
                stop = noise_next[ch];
        edges_changed = 0;
        /* A sleeping core jumps to its next cycle timer: this one keeps it from passing stop. */
        avr_cycle_timer_register(avr, stop - avr->cycle, stop_timer, NULL);
        while (avr->cycle < stop && !edges_changed) {
            avr_cycle_count_t c0 = avr->cycle;
            uint32_t pc0 = avr->pc;
            int was_sleeping = avr->state == cpu_Sleeping;
            int st = avr_run(avr);
            if (st == cpu_Done || st == cpu_Crashed)
                die("the AVR stopped (state %d) at pc 0x%x", st, avr->pc);
            /* Correction 2: after SEI/RETI one instruction runs, then interrupts are taken. */
            if (fix_bugs && avr->interrupt_state == -1)
                avr->interrupt_state = avr_has_pending_interrupts(avr);
            int was_reset = reset_seen;
            after_step(c0, pc0, was_sleeping);
            if (was_reset) {
                level_polling_off();
                if (avr->cycle < stop) /* a reset cancels every cycle timer */
                    avr_cycle_timer_register(avr, stop - avr->cycle, stop_timer, NULL);
            }
        }
        avr_cycle_timer_cancel(avr, stop_timer, NULL);
    }
    check_level_interrupts();
}

static void hexline(const char *tag, const uint8_t *b, size_t n)
{
    printf("%s ", tag);
    for (size_t i = 0; i < n; i++)
        printf("%02x", b[i]);
    printf("\n");
}

/* Correction 8: a power-on sets PORF in MCUSR. simavr sets it once, at avr_init; its avr_reset
 * (the harness's "replug", a power cycle) clears MCUSR with the other I/O registers. */
static void power_on_flag(void)
{
    if (fix_bugs)
        avr->data[A_MCUSR] |= MCUSR_PORF;
}

static int stdin_command(char *line)
{
    unsigned long long us, cyc;
    unsigned long count;
    int ch, level;
    if (strncmp(line, "send ", 5) == 0) {
        uint8_t b[2048];
        size_t n = 0;
        for (char *p = line + 5; p[0] && p[1] && n < sizeof b; p += 2) {
            unsigned v;
            if (sscanf(p, "%2x", &v) != 1)
                break;
            b[n++] = (uint8_t)v;
        }
        queue_to_avr(b, n, avr->cycle);
    } else if (sscanf(line, "run %llu", &us) == 1 || sscanf(line, "runto %llu", &cyc) == 1) {
        if (lockstep) {
            run_until(line[3] == 't' ? (avr_cycle_count_t)cyc : avr->cycle + (avr_cycle_count_t)(us * 16));
            if (from_avr_len)
                hexline("uart", from_avr, from_avr_len);
            from_avr_len = 0;
        }
        printf("ran %llu %lu\n", (unsigned long long)avr->cycle, (unsigned long)fw_us(avr->cycle));
    } else if (sscanf(line, "edge %d %d %llu", &ch, &level, &cyc) == 3 && ch >= 0 && ch <= 1) {
        add_edge((avr_cycle_count_t)cyc, ch, level != 0); /* a sensor level at an exact cycle */
    } else if (sscanf(line, "square %d %llu %llu %lu", &ch, &cyc, &us, &count) == 4 && ch >= 0 && ch <= 1) {
        /* line noise: COUNT toggles of the sensor's line, one every US cycles, from cycle CYC */
        noise_next[ch] = (avr_cycle_count_t)cyc;
        noise_half[ch] = us ? (avr_cycle_count_t)us : 1;
        noise_left[ch] = count;
    } else if (strncmp(line, "badirq", 6) == 0) {
        /* an interrupt the firmware has no handler for: INT0 enabled behind its back (falling
         * edge), and a falling edge on its pin (PD0) */
        avr->data[A_EICRA] = (uint8_t)((avr->data[A_EICRA] & ~3) | 2);
        avr->data[A_EIMSK] |= 1;
        avr_irq_t *pd0 = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 0);
        avr_raise_irq(pd0, 1);
        avr_raise_irq(pd0, 0);
    } else if (sscanf(line, "wire %d %d", &ch, &level) == 2 && ch >= 0 && ch <= 1) {
        capture_wired[ch] = level != 0;
        drive_sensor_pins();
    } else if (sscanf(line, "trace %d", &ch) == 1) {
        trace_irqs = ch;
    } else if (strncmp(line, "statsreset", 10) == 0) {
        /* measure from here: the longest pass between two watchdog kicks, the lowest stack */
        wdr_max = wdr_max_at = 0;
        wdr_count = 0;
        wdr_last = 0; /* the first interval counted starts at the next kick */
        sp_min = 0xFFFF;
        sp_min_at = 0;
    } else if (strncmp(line, "stats", 5) == 0) {
        print_stats(stdout, "");
        printf("end\n");
    } else if (strncmp(line, "info", 4) == 0) {
        printf("info origin %llu cycle %llu\n", (unsigned long long)origin_cycle, (unsigned long long)avr->cycle);
    } else if (strncmp(line, "stall", 5) == 0) {
        helper_ask("stall");
    } else if (strncmp(line, "bounce", 6) == 0) {
        helper_ask("bounce");
    } else if (strncmp(line, "unplug", 6) == 0) {
        pty_unplug();
        printf("unplugged\n");
    } else if (strncmp(line, "replug", 6) == 0) {
        avr_reset(avr); /* on_reset: the drive pin, the OC4A latch, TSM, the clock's origin */
        level_polling_off(); /* before the sensor lines are put back below */
        power_on_flag();
        /* The sensors go on pulling their lines through the MCU's reset. simavr's reset cleared
         * PINL but not the pins' IRQ values, and it passes a pin change on only when the value
         * changes: toggle each line to put its level back (capture is off after a reset). */
        for (int c = 0; c < 2; c++) {
            avr_raise_irq(sensor_irq[c], sensor_active[c] ? 1 : 0);
            avr_raise_irq(sensor_int_irq[c], sensor_active[c] ? 1 : 0);
        }
        drive_sensor_pins();
        if (link_path[0])
            pty_plug();
        else
            printf("replugged\n");
    } else if (strncmp(line, "quit", 4) == 0) {
        return 0;
    }
    fflush(stdout);
    return 1;
}

static volatile sig_atomic_t stopping;
static void on_signal(int sig)
{
    (void)sig;
    stopping = 1;
}

static double wall_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

int main(int argc, char **argv)
{
    const char *elf = NULL, *truth_path = NULL, *python = "python3", *helper = NULL;
    int seed = 0;
    char start_at = 'A';
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
#define ARG(name) (!strcmp(a, name) && v && ++i)
        if (ARG("--elf"))
            elf = v;
        else if (ARG("--link"))
            snprintf(link_path, sizeof link_path, "%s", v);
        else if (ARG("--truth"))
            truth_path = v;
        else if (ARG("--python"))
            python = v;
        else if (ARG("--helper"))
            helper = v;
        else if (ARG("--seed"))
            seed = atoi(v);
        else if (ARG("--ppm"))
            ppm = atof(v);
        else if (ARG("--rt-priority"))
            rt_priority = atoi(v);
        else if (ARG("--clock-start-us"))
            clock_start_us = (uint32_t)strtoul(v, NULL, 0);
        else if (ARG("--start-at"))
            start_at = v[0];
        else if (!strcmp(a, "--lockstep"))
            lockstep = 1;
        else if (!strcmp(a, "--emulator-bugs"))
            fix_bugs = 0;
        else
            die("usage: %s --elf ELF (--link PATH | --lockstep) [--truth CSV] [--seed N] [--ppm N] "
                "[--clock-start-us N] [--start-at A|B] [--python PY] [--helper SCRIPT] [--rt-priority N] "
                "[--emulator-bugs]",
                argv[0]);
    }
    if (!elf || (!link_path[0] && !lockstep))
        die("--elf and one of --link or --lockstep are required");
    if (clock_start_us % 32768u)
        fprintf(stderr, "usmswitch-avrsim: --clock-start-us rounded down to a timer period (32768 us)\n");

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    fflush(stdout);
    int saved_stdout = dup(1);
    dup2(2, 1); /* simavr's loader talks on stdout, which is the UART in lockstep */
    if (elf_read_firmware(elf, &fw))
        die("cannot read %s", elf);
    avr = avr_make_mcu_by_name("atmega2560");
    if (!avr)
        die("simavr has no atmega2560");
    avr_init(avr);
    avr->frequency = (uint32_t)F_CPU;
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &fw);
    avr->sleep = no_sleep;
    level_polling_off();
    fflush(stdout);
    dup2(saved_stdout, 1);
    close(saved_stdout);
    clock_ovf_addr = elf_symbol(elf, "clock_ovf");

    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (io->kind && !strcmp(io->kind, "watchdog"))
            wdt = (avr_watchdog_t *)io;
    core_reset = avr->reset;
    avr->reset = on_reset;
    power_on_flag(); /* avr_init set it already; the same for every power-on */
    timer4 = find_timer('4');
    timer5 = find_timer('5');
    if (fix_bugs) {
        fix_tifr(timer4);
        fix_tifr(timer5);
        avr_timer_t *ts[2] = {timer4, timer5};
        for (int i = 0; i < 2; i++) {
            reenable_watch(&ts[i]->overflow);
            reenable_watch(&ts[i]->icr);
            reenable_watch(&ts[i]->comp[0].interrupt);
        }
        for (avr_io_t *io = avr->io_port; io; io = io->next)
            if (io->kind && !strcmp(io->kind, "uart") && ((avr_uart_t *)io)->name == '0') {
                reenable_watch(&((avr_uart_t *)io)->rxc);
                reenable_watch(&((avr_uart_t *)io)->udrc);
            }
    }
    avr_irq_register_notify(timer4->comp[0].interrupt.irq + AVR_INT_IRQ_PENDING, on_compa, NULL);
    avr_register_io_write(avr, A_TCCR4C, w_tccr4c, NULL);
    avr_register_io_write(avr, A_TCCR4A, w_watch, NULL);
    avr_register_io_write(avr, A_PORTH, w_watch, NULL);
    avr_register_io_write(avr, A_TCNT4L, w_tcnt4l, NULL);
    avr_register_io_write(avr, A_TCNT5L, w_tcnt5l, NULL);
    avr_register_io_write(avr, A_GTCCR, w_gtccr, NULL);

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    uart_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), 0);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUTPUT, on_uart_out, NULL);
    {
        avr_io_addr_t io = AVR_DATA_TO_IO(A_UDR0);
        udr0_read = avr->io[io].r.c;
        udr0_read_param = avr->io[io].r.param;
        if (udr0_read) {
            avr->io[io].r.c = r_udr0;
            avr->io[io].r.param = NULL;
        }
    }
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XON, on_xon, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XOFF, on_xoff, NULL);
    sensor_irq[0] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('L'), 0);
    sensor_irq[1] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('L'), 1);
    sensor_int_irq[0] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 4);
    sensor_int_irq[1] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 5);

    if (!helper) {
        static char path[2048];
        ssize_t n = readlink("/proc/self/exe", path, sizeof path - 64);
        if (n < 0)
            die("readlink: %s", strerror(errno));
        path[n] = 0;
        char *slash = strrchr(path, '/');
        strcpy(slash ? slash + 1 : path, "../harness/rig_helper.py");
        helper = path;
    }
    signal(SIGPIPE, SIG_IGN);
    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    /* A harness whose parent (a test, a bench) dies goes too, rather than run on unattended. */
    prctl(PR_SET_PDEATHSIG, SIGTERM);
    if (!lockstep) {
        /* The emulated board is hardware of its own, not one more process of the host: where
         * allowed (root, CAP_SYS_NICE) it and its rig model (a child, which inherits this) run
         * ahead of the host's load, so emulated time keeps pace with the wall clock. Under
         * SCHED_OTHER, even at nice -10, a loaded 2-core machine left it 40 ms behind at times:
         * the firmware's frames then came that late, and a host timed them out as stalls. It
         * sleeps between interrupts, so the priority costs the host little CPU. */
        struct sched_param sp = {.sched_priority = rt_priority};
        if (rt_priority > 0 && sched_setscheduler(0, SCHED_FIFO, &sp) == 0)
            fprintf(stderr, "usmswitch-avrsim: running at SCHED_FIFO %d\n", rt_priority);
        else if (setpriority(PRIO_PROCESS, 0, -10) == 0)
            fprintf(stderr, "usmswitch-avrsim: running at nice -10\n");
        /* Every page in memory now and later: a page of its code or of simavr's first touched
         * mid-run would be read from disk while the emulated chip stands still (tens of ms on a
         * machine whose page cache is cold, as a fresh CI checkout's is). */
        if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0)
            fprintf(stderr, "usmswitch-avrsim: locked in memory\n");
    }
    helper_start(python, helper, seed, start_at);
    helper_ask("init");
    drive_sensor_pins();
    if (truth_path) {
        truth = fopen(truth_path, "w");
        if (!truth)
            die("%s: %s", truth_path, strerror(errno));
        fprintf(truth, "stroke,direction,start_us,depart_us,arrive_us,off_us,cut_ns\n");
        fflush(truth);
    }

    char line[8192];
    if (lockstep) {
        printf("avrsim lockstep\n");
        fflush(stdout);
        while (!stopping && fgets(line, sizeof line, stdin))
            if (!stdin_command(line))
                break;
    } else {
        pty_plug();
        fcntl(0, F_SETFL, O_NONBLOCK);
        pace_w0 = wall_s();
        pace_c0 = avr->cycle;
        size_t stdin_len = 0;
        int stdin_open = 1;
        while (!stopping) {
            avr_cycle_count_t target = wall_cycle();
            note_lag(target);
            /* Behind the wall clock (this process was not run for a while, or the machine's
             * clock jumped): catch up in chunks of CATCH_UP_CYCLES, and look at the pty only once
             * a millisecond of wall time: the pty's system calls after every 200 us chunk slowed
             * the catching up to about the wall clock's pace, so a lag lasted 100 ms. Caught up
             * in one go instead, with no look at the pty until then, the chip was deaf to the
             * host for 100-940 ms at times (the emulation barely outruns the wall clock on a
             * loaded machine): COMMANDs went unanswered. Bytes read meanwhile wait for their
             * emulated instant (queue_to_avr). */
            double looked = wall_s();
            while (target > avr->cycle + CATCH_UP_CYCLES) {
                run_until(avr->cycle + CATCH_UP_CYCLES);
                if (wall_s() - looked >= CATCH_UP_LOOK_S) {
                    pty_io();
                    looked = wall_s();
                }
                target = wall_cycle();
                note_lag(target);
            }
            run_until(target);
            if (wall_s() - looked > max_unread_s)
                max_unread_s = wall_s() - looked;
            pty_io();
            struct pollfd pf[2] = {{stdin_open ? 0 : -1, POLLIN, 0}, {pty_master, POLLIN, 0}};
            if (avr->cycle >= target) {
                /* Caught up with the wall clock: sleep until the host writes, a command comes
                 * or IDLE_NS passes (the firmware's output waits at most that long). Sleeping in
                 * poll, not spinning, keeps the harness's CPU near the emulation's own cost, so
                 * it keeps pace on a loaded machine. */
                struct timespec idle = {0, IDLE_NS};
                ppoll(pf, 2, &idle, NULL);
            } else {
                poll(pf, 2, 0);
            }
            ssize_t n = (pf[0].revents & (POLLIN | POLLHUP)) ? read(0, line + stdin_len, sizeof line - 1 - stdin_len) : -1;
            if (n == 0)
                stdin_open = 0; /* no more commands: run until SIGTERM */
            if (n > 0) {
                stdin_len += (size_t)n;
                line[stdin_len] = 0;
                char *nl;
                while ((nl = strchr(line, '\n'))) {
                    *nl = 0;
                    if (!stdin_command(line))
                        stopping = 1;
                    memmove(line, nl + 1, stdin_len - (size_t)(nl + 1 - line) + 1);
                    stdin_len -= (size_t)(nl + 1 - line);
                }
            }
        }
        pty_unplug();
        /* How far emulated time fell behind the wall clock at worst (a slow or starved host). */
        fprintf(stderr,
                "usmswitch-avrsim: max lag %.0f us (at %.3f s of emulated time), pty unread for %.1f ms at "
                "most, %lu bytes dropped\n",
                (double)max_lag * 1e6 / f_eff(), (double)max_lag_at / f_eff(), max_unread_s * 1e3, dropped_bytes);
    }
    print_stats(stderr, "usmswitch-avrsim: ");
    if (truth)
        fclose(truth);
    fclose(helper_in);
    waitpid(helper_pid, NULL, 0);
    return 0;
}
