/*
 * Tare or reset a running `fbgforce stream --control udp://HOST:PORT` (datagram layouts:
 * docs/protocol.md, "Control datagram"). Portable C99 + POSIX sockets, no dependencies:
 *
 *     cc -std=c99 -Wall -Wextra -Werror -pedantic -o control control.c
 *     ./control 127.0.0.1 9871 tare [COUNT]
 *
 * Sends the command (COUNT times, one after the other; default once) and prints the final
 * answer of each as one CSV line: seq,result,command,change_fm1..5,samples,message. A command
 * is sent again every 100 ms until its final answer (DONE, FAILED or REFUSED) arrives; the
 * stream applies it once however often it arrives (sequence numbers). Exit 0 when every
 * command was DONE, 1 when one failed or was refused, 2 when one got no answer within 10 s.
 * Fields are written and read byte by byte as little-endian, right on any host byte order.
 */
#define _POSIX_C_SOURCE 200112L
#include <arpa/inet.h>
#include <netinet/in.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

#define COMMAND_SIZE 24
#define ACK_SIZE 124
#define MESSAGE_BYTES 76
#define RESULT_PENDING 3
#define RESEND_MS 100
#define TIMEOUT_MS 10000

typedef struct {
    uint32_t session, seq;
    uint16_t command, result;
    int32_t change_fm[5]; /* the baseline's change per grating (FBG 1..4, T), 1/1000 pm */
    uint32_t samples;     /* samples averaged */
    char message[MESSAGE_BYTES + 1];
} fbg_ack;

static uint32_t le32(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint16_t le16(const unsigned char *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static void put16(unsigned char *p, uint16_t v)
{
    p[0] = (unsigned char)(v & 0xFFu);
    p[1] = (unsigned char)(v >> 8);
}

static void put32(unsigned char *p, uint32_t v)
{
    put16(p, (uint16_t)(v & 0xFFFFu));
    put16(p + 2, (uint16_t)(v >> 16));
}

/* CRC-32 (zlib/Ethernet: reflected 0xEDB88320, init and final XOR 0xFFFFFFFF), bitwise. */
static uint32_t crc32(const unsigned char *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    size_t i;
    int b;
    for (i = 0; i < n; i++) {
        c ^= p[i];
        for (b = 0; b < 8; b++) c = (c & 1u) ? (c >> 1) ^ 0xEDB88320u : c >> 1;
    }
    return c ^ 0xFFFFFFFFu;
}

static void encode_command(unsigned char d[COMMAND_SIZE], uint32_t session, uint32_t seq,
                           uint16_t command)
{
    memcpy(d, "FBGC", 4);
    put16(d + 4, 1);
    put16(d + 6, COMMAND_SIZE);
    put32(d + 8, session);
    put32(d + 12, seq);
    put16(d + 16, command);
    put16(d + 18, 0);
    put32(d + 20, crc32(d, 20));
}

/* 0 on success; -1 if the datagram is not a valid version-1 acknowledgement. */
static int decode_ack(const unsigned char *d, size_t n, fbg_ack *a)
{
    int i;
    if (n != ACK_SIZE || memcmp(d, "FBGA", 4) != 0) return -1;
    if (le16(d + 4) != 1 || le16(d + 6) != ACK_SIZE) return -1;
    if (crc32(d, ACK_SIZE - 4) != le32(d + ACK_SIZE - 4)) return -1;
    a->session = le32(d + 8);
    a->seq = le32(d + 12);
    a->command = le16(d + 16);
    a->result = le16(d + 18);
    for (i = 0; i < 5; i++) a->change_fm[i] = (int32_t)le32(d + 20 + 4 * i);
    a->samples = le32(d + 40);
    memcpy(a->message, d + 44, MESSAGE_BYTES);
    a->message[MESSAGE_BYTES] = '\0';
    return 0;
}

static long now_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long)ts.tv_sec * 1000L + ts.tv_nsec / 1000000L;
}

/* Send until the final answer of (session, seq) arrives: 0 with *a filled, -1 on timeout. */
static int transact(int fd, const struct sockaddr_in *to, uint32_t session, uint32_t seq,
                    uint16_t command, fbg_ack *a)
{
    unsigned char cmd[COMMAND_SIZE], buf[512];
    long end = now_ms() + TIMEOUT_MS;
    encode_command(cmd, session, seq, command);
    while (now_ms() < end) {
        long resend_at = now_ms() + RESEND_MS;
        if (sendto(fd, cmd, sizeof cmd, 0, (const struct sockaddr *)to, sizeof *to) < 0)
            perror("sendto");
        for (;;) {
            fd_set fds;
            struct timeval tv;
            ssize_t n;
            long left = resend_at - now_ms();
            if (left <= 0) break;
            tv.tv_sec = left / 1000;
            tv.tv_usec = (left % 1000) * 1000;
            FD_ZERO(&fds);
            FD_SET(fd, &fds);
            if (select(fd + 1, &fds, NULL, NULL, &tv) <= 0) break;
            n = recv(fd, buf, sizeof buf, 0);
            if (n < 0 || decode_ack(buf, (size_t)n, a) != 0) continue; /* garbage */
            if (a->session != session || a->seq != seq) continue; /* a late earlier answer */
            if (a->result != RESULT_PENDING) return 0;
        }
    }
    return -1;
}

int main(int argc, char **argv)
{
    static const char *const results[4] = {"DONE", "FAILED", "REFUSED", "PENDING"};
    struct sockaddr_in to;
    uint16_t command;
    uint32_t session, seq;
    long count, i;
    int fd, code = 0;

    if (argc < 4 || (strcmp(argv[3], "tare") != 0 && strcmp(argv[3], "reset") != 0)) {
        fprintf(stderr, "usage: %s ADDRESS PORT tare|reset [COUNT]\n", argv[0]);
        return 2;
    }
    command = strcmp(argv[3], "tare") == 0 ? 1 : 2;
    count = argc > 4 ? atol(argv[4]) : 1;
    fd = socket(AF_INET, SOCK_DGRAM, 0);
    if (fd < 0) {
        perror("socket");
        return 2;
    }
    memset(&to, 0, sizeof to);
    to.sin_family = AF_INET;
    to.sin_port = htons((uint16_t)atoi(argv[2]));
    if (inet_pton(AF_INET, argv[1], &to.sin_addr) != 1) {
        fprintf(stderr, "%s: not an IPv4 address\n", argv[1]);
        return 2;
    }
    /* A new session per run: the stream takes a restarted client for a new one. */
    session = (uint32_t)time(NULL) ^ ((uint32_t)getpid() << 16) ^ (uint32_t)now_ms();
    for (i = 0, seq = 0; i < count; i++) {
        fbg_ack a;
        int k;
        seq++;
        if (transact(fd, &to, session, seq, command, &a) != 0) {
            fprintf(stderr, "no answer to %s #%lu\n", argv[3], (unsigned long)seq);
            close(fd);
            return 2;
        }
        printf("%lu,%s,%u", (unsigned long)a.seq, results[a.result < 4 ? a.result : 2],
               (unsigned)a.command);
        for (k = 0; k < 5; k++) printf(",%ld", (long)a.change_fm[k]);
        printf(",%lu,%s\n", (unsigned long)a.samples, a.message);
        fflush(stdout);
        if (a.result != 0) code = 1;
    }
    close(fd);
    return code;
}
