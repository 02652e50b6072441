/* usmswitch firmware: the protocol core, docs/mcu-protocol.md, behaviour kept identical to the
 * reference emulator sim/mcu_emulator.py (the conformance suite runs both). */
#include "core.h"

#include "proto.h"

enum stroke_state { SS_NONE = 0, SS_SCHEDULED, SS_RUNNING, SS_DONE };

struct stroke {
    uint16_t id;
    uint8_t direction; /* 0 on (A to B), 1 off (B to A) */
    uint8_t state;     /* enum stroke_state */
    uint8_t departed, late, missed; /* missed: a stamp of it is a missed edge's */
    uint32_t delay_us, timeout_us;
    uint32_t t_cmd_us, t_due_us, t_start_us, t_depart_us, t_arrive_us;
};

static struct {
    /* receive */
    uint8_t rx_buf[MAX_ENCODED];
    uint8_t rx_len;
    uint8_t rx_overrun;
    uint16_t rx_expected;
    uint8_t rx_have_expected;
    uint16_t rx_errors, rx_lost;
    /* transmit */
    uint16_t tx_seq;
    /* session */
    uint8_t reset_cause;
    uint8_t synced;
    uint8_t minor; /* the session's minor version: 1.2 adds EDGE.flags and PONG's two counters */
    uint32_t watchdog_us;
    uint32_t last_host_us;
    /* strokes */
    uint8_t armed;
    struct stroke arm; /* the armed stroke, valid when armed */
    uint8_t have_cur;
    struct stroke cur; /* the commanded stroke (SS_SCHEDULED/RUNNING) or the last one (SS_DONE) */
    /* interrupt events the board lost (its queue full) and edges its capture units missed (found
     * by reading the pins back), since the last HELLO; PONG (1.2) reports both */
    uint16_t events_lost, edges_missed;
    uint16_t lost_unreported; /* lost, and not yet in a FAULT EVENTS_LOST */
    uint8_t lost_reported;    /* a FAULT EVENTS_LOST went out at lost_report_us */
    uint32_t lost_report_us;
} S;

/* At most one FAULT EVENTS_LOST in this long while no stroke runs (the PONG counter has them all):
 * a storm of edges would otherwise fill the line with faults. */
#define LOST_REPORT_US 10000UL

void core_init(void)
{
    uint8_t *p = (uint8_t *)&S;
    for (uint16_t i = 0; i < sizeof S; i++)
        p[i] = 0;
}

void core_get_stats(struct core_stats *out)
{
    out->rx_errors = S.rx_errors;
    out->rx_lost = S.rx_lost;
    out->tx_seq = S.tx_seq;
    out->synced = S.synced;
}

/* ---- transmit ---- */
static uint8_t tx_payload[MAX_PAYLOAD];

/* Build the frame around a body already written at tx_payload + 3 and send it. */
static void send(uint8_t type, uint8_t body_len)
{
    uint8_t enc[MAX_ENCODED + 1];
    uint8_t n = (uint8_t)(3 + body_len);
    tx_payload[0] = type;
    put_u16(tx_payload + 1, S.tx_seq++);
    put_u16(tx_payload + n, crc16(tx_payload, n));
    uint8_t m = cobs_encode(tx_payload, (uint8_t)(n + 2), enc);
    enc[m++] = 0;
    hal_tx(enc, m);
}

static uint8_t *body(void) { return tx_payload + 3; }

static void send_ack(uint8_t acked_type, uint16_t acked_seq, uint8_t status, uint16_t stroke, uint32_t t_us)
{
    uint8_t *p = body();
    *p++ = acked_type;
    p = put_u16(p, acked_seq);
    *p++ = status;
    p = put_u16(p, stroke);
    put_u32(p, t_us);
    send(MT_ACK, 10);
}

static void send_fault(uint8_t code, uint32_t t_us, uint16_t detail)
{
    uint8_t *p = body();
    *p++ = code;
    p = put_u32(p, t_us);
    put_u16(p, detail);
    send(MT_FAULT, 7);
}

static void send_edge(uint8_t channel, uint8_t level, uint32_t t_us, uint8_t flags)
{
    uint8_t *p = body();
    *p++ = channel;
    *p++ = level;
    p = put_u32(p, t_us);
    if (S.minor >= 2) {
        *p = flags;
        send(MT_EDGE, 7);
    } else {
        send(MT_EDGE, 6); /* a 1.0/1.1 host gets the edge without its flags */
    }
}

void core_boot(uint8_t reset_cause)
{
    S.reset_cause = reset_cause;
    uint8_t *p = body();
    *p++ = reset_cause;
    put_u16(p, FW_VERSION);
    send(MT_BOOT, 3);
}

/* ---- strokes ---- */
static uint8_t running(void) { return S.have_cur && S.cur.state != SS_DONE; }

/* Drive off, then STROKE, then STOPPED (the order the protocol requires). */
static void end_stroke(uint32_t t_us, uint8_t reason, uint8_t flags)
{
    struct stroke *st = &S.cur;
    uint8_t started = st->state == SS_RUNNING;
    hal_drive_off();
    st->state = SS_DONE;
    if (st->departed)
        flags |= SF_DEPARTED;
    if (st->late)
        flags |= SF_LATE;
    if (st->missed)
        flags |= SF_MISSED_EDGE;
    uint8_t *p = body();
    p = put_u16(p, st->id);
    *p++ = st->direction;
    *p++ = flags;
    p = put_u32(p, st->t_cmd_us);
    p = put_u32(p, started ? st->t_start_us : 0);
    p = put_u32(p, st->departed ? st->t_depart_us : 0);
    put_u32(p, (flags & SF_ARRIVED) ? st->t_arrive_us : 0);
    send(MT_STROKE, 20);
    p = body();
    p = put_u16(p, st->id);
    *p++ = reason;
    put_u32(p, t_us);
    send(MT_STOPPED, 7);
}

void core_start(uint32_t t_us)
{
    struct stroke *st = &S.cur;
    if (!S.have_cur || st->state != SS_SCHEDULED)
        return; /* a start the core already cancelled (STOP raced the compare) */
    int32_t late = (int32_t)(t_us - st->t_due_us);
    st->state = SS_RUNNING;
    st->t_start_us = t_us;
    st->late = late > 0;
    uint8_t *p = body();
    p = put_u16(p, st->id);
    *p++ = st->direction;
    p = put_u32(p, t_us);
    put_u32(p, late > 0 ? (uint32_t)late : 0);
    send(MT_START, 11);
    /* Already at the destination: the stroke is over as it starts. */
    uint8_t dest = st->direction == 0 ? 1 : 0;
    uint8_t sensors = hal_sensors();
    if (sensors & (1u << dest)) {
        st->t_arrive_us = t_us;
        end_stroke(t_us, SR_ARRIVED, SF_ARRIVED);
        return;
    }
    /* Not at the source either (a jam left the mover between, or a sensor is dead): the stroke
     * runs (its stall limit still holds), and a 1.2 host hears of it. */
    if (S.minor >= 2 && !(sensors & (1u << (dest ^ 1))))
        send_fault(FC_SENSORS, t_us, sensors);
}

void core_edge(uint8_t channel, uint8_t level, uint32_t t_us, uint8_t flags)
{
    struct stroke *st = &S.cur;
    uint8_t live = S.have_cur && st->state == SS_RUNNING;
    uint8_t source = st->direction == 0 ? 0 : 1;
    if (flags & EF_MISSED)
        S.edges_missed++;
    if (live && channel == (source ^ 1) && level) {
        /* Arrival: the external interrupt has already cut the drive (STOP_ON_ARRIVAL);
         * hal_drive_off() in end_stroke makes sure of it. */
        st->t_arrive_us = t_us;
        if (flags & EF_MISSED)
            st->missed = 1;
        send_edge(channel, level, t_us, flags);
        end_stroke(t_us, SR_ARRIVED, SF_ARRIVED);
        return;
    }
    if (live && channel == source && !level && !st->departed) {
        st->departed = 1;
        st->t_depart_us = t_us;
        if (flags & EF_MISSED)
            st->missed = 1;
    }
    send_edge(channel, level, t_us, flags);
}

uint8_t core_wants_arrival(uint8_t channel)
{
    struct stroke *st = &S.cur;
    return S.have_cur && st->state == SS_RUNNING && channel == (st->direction == 0 ? 1 : 0);
}

static void report_lost(uint32_t now)
{
    uint16_t n = S.lost_unreported;
    S.lost_unreported = 0;
    S.lost_reported = 1;
    S.lost_report_us = now;
    send_fault(FC_EVENTS_LOST, now, n);
}

void core_events_lost(uint16_t n, uint32_t now)
{
    S.events_lost = (uint16_t)(S.events_lost + n);
    uint32_t unreported = (uint32_t)S.lost_unreported + n;
    S.lost_unreported = unreported > 0xFFFFu ? 0xFFFFu : (uint16_t)unreported;
    /* A stroke whose edges may be among the lost cannot be told: it ends, now, as a fault. */
    if (running()) {
        hal_drive_off(); /* first: building a frame takes tens of microseconds */
        report_lost(now);
        end_stroke(now, SR_FAULT, SF_EVENTS_LOST);
    } else if (!S.lost_reported || now - S.lost_report_us >= LOST_REPORT_US) {
        report_lost(now);
    }
}

uint32_t core_poll(void)
{
    uint32_t now = hal_now_us();
    if (S.synced && now - S.last_host_us > S.watchdog_us) {
        S.synced = 0;
        S.armed = 0;
        uint32_t ms = S.watchdog_us / 1000;
        if (running())
            hal_drive_off(); /* first: building a frame takes tens of microseconds */
        send_fault(FC_HOST_SILENT, now, ms > 0xFFFF ? 0xFFFF : (uint16_t)ms);
        if (running())
            end_stroke(now, SR_WATCHDOG, SF_WATCHDOG);
    }
    struct stroke *st = &S.cur;
    /* The stall check runs whenever the drive may be on, whatever the core's state: a running
     * stroke from its start, a scheduled one whose drive is on before its START came through
     * from the instant on_command expects it on (t_start_us until then). */
    uint8_t on = hal_drive_is_on();
    uint8_t timed = S.have_cur && (st->state == SS_RUNNING || (st->state == SS_SCHEDULED && on));
    uint32_t from = st->t_start_us;
    if (timed && (int32_t)(now - from) >= 0 && now - from >= st->timeout_us) {
        uint32_t ms = st->timeout_us / 1000;
        hal_drive_off(); /* first: building a frame takes tens of microseconds */
        send_fault(FC_STALL, now, ms > 0xFFFF ? 0xFFFF : (uint16_t)ms);
        end_stroke(now, SR_STALL, SF_STALL);
        timed = 0;
    } else if (on && !running()) {
        /* The drive on with no stroke of the core's: cut it, and say so. */
        hal_drive_off();
        send_fault(FC_DRIVE, now, 1);
    }
    if (S.lost_unreported && now - S.lost_report_us >= LOST_REPORT_US)
        report_lost(now);
    /* The next instant a check above can fire: the watchdog one microsecond past its period,
     * the stroke timeout at start + timeout, the next report of lost events. */
    uint32_t left = UINT32_MAX;
    if (S.synced)
        left = S.watchdog_us + 1 - (now - S.last_host_us);
    if (timed) {
        uint32_t stall = (int32_t)(now - from) >= 0 ? st->timeout_us - (now - from) : st->timeout_us;
        if (stall < left)
            left = stall;
    }
    if (S.lost_unreported) {
        uint32_t next = LOST_REPORT_US - (now - S.lost_report_us);
        if (next < left)
            left = next;
    }
    return left;
}

/* ---- requests ---- */
static void on_hello(uint16_t seq, const uint8_t *b, uint32_t now)
{
    if (running())
        end_stroke(now, SR_RESET, SF_HOST_STOP);
    S.armed = 0;
    /* A new session: the last one's stroke is forgotten, so its id cannot make the new host's
     * first COMMAND a "retransmission" (issue 33: a host restarted on a board that was not
     * reset numbered its strokes from 1 again, and stroke 1 never started). */
    S.have_cur = 0;
    S.events_lost = S.edges_missed = S.lost_unreported = 0;
    S.lost_reported = 0;
    S.tx_seq = 0;
    S.rx_expected = (uint16_t)(seq + 1);
    S.rx_have_expected = 1;
    S.rx_lost = 0;
    S.rx_errors = 0;
    uint16_t wd_ms = get_u16(b + 2);
    S.watchdog_us = (uint32_t)(wd_ms < 10 ? 10 : wd_ms) * 1000UL;
    S.last_host_us = now;
    S.synced = b[0] == PROTO_MAJOR;
    /* The session speaks the lower of the two minor versions, and says which: a 1.0 host gets the
     * 1.0 layout, a 1.1 host the reset cause after it. */
    uint8_t minor = b[0] == PROTO_MAJOR && b[1] < PROTO_MINOR ? b[1] : PROTO_MINOR;
    S.minor = minor;
    uint8_t *p = body();
    *p++ = PROTO_MAJOR;
    *p++ = minor;
    p = put_u32(p, ALL_CAPS);
    p = put_u16(p, FW_VERSION);
    p = put_u32(p, now);
    p = put_u32(p, MAX_DELAY_US);
    if (minor >= 1) {
        *p = S.reset_cause;
        send(MT_HELLO_ACK, 17);
    } else {
        send(MT_HELLO_ACK, 16);
    }
}

static void on_ping(const uint8_t *b, uint32_t now)
{
    uint8_t state = 0;
    if (S.synced)
        state |= STF_SYNCED;
    if (S.armed)
        state |= STF_ARMED;
    if (hal_drive_is_on())
        state |= STF_DRIVE_ON;
    uint8_t sensors = hal_sensors();
    if (sensors & 1)
        state |= STF_SENSOR_A;
    if (sensors & 2)
        state |= STF_SENSOR_B;
    uint8_t *p = body();
    p = put_u32(p, get_u32(b));
    p = put_u32(p, now);
    *p++ = state;
    p = put_u16(p, S.rx_errors);
    p = put_u16(p, S.rx_lost);
    if (S.minor >= 2) {
        p = put_u16(p, S.events_lost);
        put_u16(p, S.edges_missed);
        send(MT_PONG, 17);
    } else {
        send(MT_PONG, 13);
    }
}

static void on_arm(uint16_t seq, const uint8_t *b, uint32_t now)
{
    uint16_t id = get_u16(b);
    uint8_t dir = b[2];
    uint32_t delay = get_u32(b + 3), timeout = get_u32(b + 7);
    if (running()) {
        send_ack(MT_ARM, seq, ST_BUSY, id, now);
        return;
    }
    if (dir > 1 || delay > MAX_DELAY_US || timeout < 1000UL || timeout > 10000000UL) {
        send_ack(MT_ARM, seq, ST_BAD_ARG, id, now);
        return;
    }
    S.armed = 1;
    S.arm.id = id;
    S.arm.direction = dir;
    S.arm.delay_us = delay;
    S.arm.timeout_us = timeout;
    send_ack(MT_ARM, seq, ST_OK, id, now);
}

static void on_command(uint16_t seq, const uint8_t *b, uint32_t now)
{
    uint16_t id = get_u16(b);
    uint32_t t_cmd = get_u32(b + 2);
    uint8_t at = b[6];
    if (S.have_cur && S.cur.id == id) {
        send_ack(MT_COMMAND, seq, ST_OK, id, S.cur.t_cmd_us); /* a retransmission */
        return;
    }
    if (running()) {
        send_ack(MT_COMMAND, seq, ST_BUSY, id, now);
        return;
    }
    if (!S.armed || S.arm.id != id) {
        send_ack(MT_COMMAND, seq, ST_NOT_ARMED, id, now);
        return;
    }
    if (at) {
        uint32_t skew = t_cmd - now;
        uint32_t back = now - t_cmd;
        if ((skew < back ? skew : back) > MAX_COMMAND_SKEW_US) {
            send_ack(MT_COMMAND, seq, ST_BAD_TIME, id, now);
            return;
        }
    } else {
        t_cmd = now;
    }
    S.armed = 0;
    S.cur = S.arm;
    S.have_cur = 1;
    struct stroke *st = &S.cur;
    st->state = SS_SCHEDULED;
    st->departed = 0;
    st->late = 0;
    st->missed = 0;
    st->t_cmd_us = t_cmd;
    st->t_due_us = t_cmd + st->delay_us;
    send_ack(MT_COMMAND, seq, ST_OK, id, t_cmd);
    hal_drive_schedule(st->t_due_us, st->direction, st->direction == 0 ? 1 : 0);
    /* Until its START, the stroke's stall limit runs from the instant the drive goes on: the due
     * one, or, for a COMMAND that came after it (a held-up host), now, when it went on at once.
     * From the due instant, a start later than the limit was cut as a stall a frame after it. */
    uint32_t after = hal_now_us();
    st->t_start_us = (int32_t)(after - st->t_due_us) > 0 ? after : st->t_due_us;
}

static void on_stop(uint16_t seq, uint32_t now)
{
    if (running())
        end_stroke(now, SR_HOST, SF_HOST_STOP);
    S.armed = 0;
    send_ack(MT_STOP, seq, ST_OK, S.have_cur ? S.cur.id : 0, now);
}

static void on_frame(const uint8_t *pl, uint8_t n)
{
    if (n < 5 || n > MAX_PAYLOAD || crc16(pl, (uint8_t)(n - 2)) != get_u16(pl + n - 2)) {
        S.rx_errors++;
        return;
    }
    uint8_t type = pl[0];
    uint16_t seq = get_u16(pl + 1);
    const uint8_t *b = pl + 3;
    /* A known type must have one of its sizes; an unknown one (a newer minor version) is answered. */
    if (!msg_body_size_ok(type, (uint8_t)(n - 5))) {
        S.rx_errors++;
        return;
    }
    uint32_t now = hal_now_us();
    if (type == MT_HELLO) {
        on_hello(seq, b, now);
        return;
    }
    if (S.rx_have_expected) {
        uint16_t gap = (uint16_t)(seq - S.rx_expected);
        if (gap != 0 && gap < 0x8000u)
            S.rx_lost = (uint16_t)(S.rx_lost + gap);
    }
    S.rx_expected = (uint16_t)(seq + 1);
    S.rx_have_expected = 1;
    if (!S.synced) {
        if (type == MT_PING)
            on_ping(b, now); /* a tripped device still says it is alive and unsynced */
        else
            send_ack(type, seq, ST_NOT_SYNCED, 0, now);
        return;
    }
    S.last_host_us = now;
    switch (type) {
    case MT_PING: on_ping(b, now); break;
    case MT_ARM: on_arm(seq, b, now); break;
    case MT_COMMAND: on_command(seq, b, now); break;
    case MT_STOP: on_stop(seq, now); break;
    default: send_ack(type, seq, ST_UNKNOWN_TYPE, 0, now); break;
    }
}

void core_rx_byte(uint8_t c)
{
    if (c != 0) {
        if (S.rx_len >= MAX_ENCODED)
            S.rx_overrun = 1;
        else
            S.rx_buf[S.rx_len++] = c;
        return;
    }
    uint8_t len = S.rx_len;
    S.rx_len = 0;
    if (S.rx_overrun) {
        S.rx_overrun = 0;
        S.rx_errors++;
        return;
    }
    if (len == 0)
        return; /* idle line */
    uint8_t payload[MAX_ENCODED];
    int16_t n = cobs_decode(S.rx_buf, len, payload);
    if (n < 0) {
        S.rx_errors++;
        return;
    }
    on_frame(payload, (uint8_t)n);
}
