/* usmswitch firmware: the protocol core, docs/mcu-protocol.md, behaviour kept identical to the
 * reference emulator sim/mcu_emulator.py (the conformance suite runs both). */
#include "core.h"

#include "proto.h"

enum stroke_state { SS_NONE = 0, SS_SCHEDULED, SS_RUNNING, SS_DONE };

struct stroke {
    uint16_t id;
    uint8_t direction; /* 0 on (A to B), 1 off (B to A) */
    uint8_t state;     /* enum stroke_state */
    uint8_t departed, late;
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
    uint32_t watchdog_us;
    uint32_t last_host_us;
    /* strokes */
    uint8_t armed;
    struct stroke arm; /* the armed stroke, valid when armed */
    uint8_t have_cur;
    struct stroke cur; /* the commanded stroke (SS_SCHEDULED/RUNNING) or the last one (SS_DONE) */
} S;

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

static void send_edge(uint8_t channel, uint8_t level, uint32_t t_us)
{
    uint8_t *p = body();
    *p++ = channel;
    *p++ = level;
    put_u32(p, t_us);
    send(MT_EDGE, 6);
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
    if (hal_sensors() & (1u << dest)) {
        st->t_arrive_us = t_us;
        end_stroke(t_us, SR_ARRIVED, SF_ARRIVED);
    }
}

void core_edge(uint8_t channel, uint8_t level, uint32_t t_us)
{
    struct stroke *st = &S.cur;
    uint8_t live = S.have_cur && st->state == SS_RUNNING;
    uint8_t source = st->direction == 0 ? 0 : 1;
    if (live && channel == (source ^ 1) && level) {
        /* Arrival: the capture interrupt has already cut the drive (STOP_ON_ARRIVAL);
         * hal_drive_off() in end_stroke makes sure of it. */
        st->t_arrive_us = t_us;
        send_edge(channel, level, t_us);
        end_stroke(t_us, SR_ARRIVED, SF_ARRIVED);
        return;
    }
    if (live && channel == source && !level && !st->departed) {
        st->departed = 1;
        st->t_depart_us = t_us;
    }
    send_edge(channel, level, t_us);
}

uint32_t core_poll(void)
{
    uint32_t now = hal_now_us();
    if (S.synced && now - S.last_host_us > S.watchdog_us) {
        S.synced = 0;
        S.armed = 0;
        uint32_t ms = S.watchdog_us / 1000;
        send_fault(FC_HOST_SILENT, now, ms > 0xFFFF ? 0xFFFF : (uint16_t)ms);
        if (running())
            end_stroke(now, SR_WATCHDOG, SF_WATCHDOG);
    }
    struct stroke *st = &S.cur;
    if (S.have_cur && st->state == SS_RUNNING && now - st->t_start_us >= st->timeout_us) {
        uint32_t ms = st->timeout_us / 1000;
        send_fault(FC_STALL, now, ms > 0xFFFF ? 0xFFFF : (uint16_t)ms);
        end_stroke(now, SR_STALL, SF_STALL);
    }
    /* The next instant a check above can fire: the watchdog one microsecond past its period,
     * the stroke timeout at start + timeout. */
    uint32_t left = UINT32_MAX;
    if (S.synced)
        left = S.watchdog_us + 1 - (now - S.last_host_us);
    if (S.have_cur && st->state == SS_RUNNING) {
        uint32_t stall = st->timeout_us - (now - st->t_start_us);
        if (stall < left)
            left = stall;
    }
    return left;
}

/* ---- requests ---- */
static void on_hello(uint16_t seq, const uint8_t *b, uint32_t now)
{
    if (running())
        end_stroke(now, SR_RESET, SF_HOST_STOP);
    S.armed = 0;
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
    put_u16(p, S.rx_lost);
    send(MT_PONG, 13);
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
    st->t_cmd_us = t_cmd;
    st->t_due_us = t_cmd + st->delay_us;
    send_ack(MT_COMMAND, seq, ST_OK, id, t_cmd);
    hal_drive_schedule(st->t_due_us, st->direction, st->direction == 0 ? 1 : 0);
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
    int8_t size = msg_body_size(type);
    /* A known type must have its size; an unknown one (a newer minor version) is answered. */
    if (size >= 0 && size != (int8_t)(n - 5)) {
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
