/* Native driver of the firmware's protocol core with a fake hardware layer.
 *
 * Reads commands on stdin, one a line, and prints what the core did:
 *   clock N           set the fake microsecond clock
 *   sensors N         bit 0 sensor A active, bit 1 sensor B active
 *   rx HEX            bytes from the host (wire bytes, delimiters included)
 *   start T           the drive went on at T (the hardware layer's compare fired)
 *   edge CH LEVEL T [FLAGS]  a sensor edge (FLAGS: EF_MISSED 1, EF_CUT 2)
 *   lost N            the hardware layer lost N interrupt events
 *   drive N           the fake drive output on (1) or off (0), behind the core's back
 *   poll              the main loop's timeout check
 *   stats             print "stats rx_errors rx_lost tx_seq synced"
 *   crc HEX           print "crc XXXX" of the bytes
 *   cobs HEX          print "cobs HEX" (encoded, no delimiter)
 *   uncobs HEX        print "uncobs HEX" or "uncobs error"
 *   size TYPE         print "size N"
 * Output lines: "tx HEX" for each frame the core sent (delimiter included), "hal schedule DUE DIR
 * DEST" and "hal off" for drive calls. The Python tests (test_core_native.py) drive it. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "core.h"
#include "proto.h"

static uint32_t fake_now;
static uint8_t fake_sensors;
static uint8_t fake_drive;
static uint8_t txbuf[4096];
static size_t txlen;

uint32_t hal_now_us(void) { return fake_now; }

void hal_tx(const uint8_t *buf, uint8_t len)
{
    memcpy(txbuf + txlen, buf, len);
    txlen += len;
}

void hal_drive_schedule(uint32_t due_us, uint8_t direction, uint8_t dest)
{
    printf("hal schedule %lu %u %u\n", (unsigned long)due_us, direction, dest);
    fake_drive = 1;
}

void hal_drive_off(void)
{
    printf("hal off\n");
    fake_drive = 0;
}

uint8_t hal_drive_is_on(void) { return fake_drive; }

uint8_t hal_sensors(void) { return fake_sensors; }

static void flush_tx(void)
{
    size_t start = 0;
    for (size_t i = 0; i < txlen; i++) {
        if (txbuf[i] != 0)
            continue;
        printf("tx ");
        for (size_t k = start; k <= i; k++)
            printf("%02x", txbuf[k]);
        printf("\n");
        start = i + 1;
    }
    txlen = 0;
}

static size_t parse_hex(const char *s, uint8_t *out, size_t cap)
{
    size_t n = 0;
    while (s[0] && s[1] && n < cap) {
        if (s[0] == ' ' || s[0] == '\n') {
            s++;
            continue;
        }
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1)
            break;
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static void print_hex(const char *tag, const uint8_t *b, size_t n)
{
    printf("%s ", tag);
    for (size_t i = 0; i < n; i++)
        printf("%02x", b[i]);
    printf("\n");
}

int main(void)
{
    char line[4096];
    uint8_t buf[1024], out[1100];
    core_init();
    while (fgets(line, sizeof line, stdin)) {
        unsigned long a, b, c, d = 0;
        if (sscanf(line, "clock %lu", &a) == 1) {
            fake_now = (uint32_t)a;
        } else if (sscanf(line, "sensors %lu", &a) == 1) {
            fake_sensors = (uint8_t)a;
        } else if (strncmp(line, "rx ", 3) == 0) {
            size_t n = parse_hex(line + 3, buf, sizeof buf);
            for (size_t i = 0; i < n; i++)
                core_rx_byte(buf[i]);
        } else if (sscanf(line, "boot %lu", &a) == 1) {
            core_boot((uint8_t)a);
        } else if (sscanf(line, "start %lu", &a) == 1) {
            core_start((uint32_t)a);
        } else if (sscanf(line, "edge %lu %lu %lu %lu", &a, &b, &c, &d) >= 3) {
            core_edge((uint8_t)a, (uint8_t)b, (uint32_t)c, (uint8_t)d); /* d: EF_* flags */
        } else if (sscanf(line, "drive %lu", &a) == 1) {
            fake_drive = (uint8_t)a;
        } else if (sscanf(line, "lost %lu", &a) == 1) {
            core_events_lost((uint16_t)a, fake_now);
        } else if (strncmp(line, "poll", 4) == 0) {
            core_poll();
        } else if (strncmp(line, "stats", 5) == 0) {
            struct core_stats st;
            core_get_stats(&st);
            printf("stats %u %u %u %u\n", st.rx_errors, st.rx_lost, st.tx_seq, st.synced);
        } else if (strncmp(line, "crc ", 4) == 0) {
            size_t n = parse_hex(line + 4, buf, sizeof buf);
            printf("crc %04x\n", crc16(buf, (uint8_t)n));
        } else if (strncmp(line, "cobs ", 5) == 0) {
            size_t n = parse_hex(line + 5, buf, 254);
            print_hex("cobs", out, cobs_encode(buf, (uint8_t)n, out));
        } else if (strncmp(line, "uncobs ", 7) == 0) {
            size_t n = parse_hex(line + 7, buf, 255);
            int16_t m = cobs_decode(buf, (uint8_t)n, out);
            if (m < 0)
                printf("uncobs error\n");
            else
                print_hex("uncobs", out, (size_t)m);
        } else if (sscanf(line, "size %lx", &a) == 1) {
            printf("size %d\n", msg_body_size((uint8_t)a));
        } else if (line[0] != '\n' && line[0] != '#') {
            fprintf(stderr, "core_test: unknown command: %s", line);
            return 2;
        }
        flush_tx();
        fflush(stdout);
    }
    return 0;
}
