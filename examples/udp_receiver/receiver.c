/*
 * Receiver of `fbgforce stream --publish udp://HOST:PORT` (datagram layout: docs/protocol.md,
 * "Estimate datagram"). Portable C99 + POSIX sockets, no dependencies:
 *
 *     cc -std=c99 -Wall -Wextra -Werror -pedantic -o receiver receiver.c
 *     ./receiver 127.0.0.1 9870 [COUNT]
 *
 * Prints one CSV line per valid datagram (seq,sample_seq,t_us,status,contact,conf_q15,
 * force_mN,x_um,y_um) and, on stderr at the end, how many datagrams were bad, missing
 * (publication counter gaps), duplicated (the last counter again: dropped) and how often the
 * publisher restarted (its counter went backwards; counting goes on from there). The stream's
 * status record (once a second, docs/protocol.md "Status record") is printed on stderr as it
 * arrives and counted.
 * Fields are read byte by byte as little-endian, so the code is right on any host byte order.
 */
#define _POSIX_C_SOURCE 200112L
#include <arpa/inet.h>
#include <netinet/in.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#define DATAGRAM_SIZE 48
#define CRC_OFFSET 44
#define STATUS_SIZE 92
#define STATUS_CRC_OFFSET 88

typedef struct {
    uint32_t seq;          /* publication counter */
    uint32_t sample_seq;   /* interrogator sample counter */
    int64_t t_us;          /* device timestamp, us (-1: none) */
    uint32_t status;       /* runtime status flags */
    uint8_t contact;       /* 0/1 */
    uint16_t conf_q15;     /* contact confidence / 32768 */
    int32_t force_mN;
    int32_t x_um;
    int32_t y_um;
} fbg_estimate;

static uint32_t le32(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint16_t le16(const unsigned char *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

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

/* 0 on success; -1 if the datagram is not a valid version-1 estimate. */
static int decode(const unsigned char *d, size_t n, fbg_estimate *e)
{
    uint64_t t;
    if (n != DATAGRAM_SIZE || memcmp(d, "FBGO", 4) != 0) return -1;
    if (le16(d + 4) != 1 || le16(d + 6) != DATAGRAM_SIZE) return -1;
    if (crc32(d, CRC_OFFSET) != le32(d + CRC_OFFSET)) return -1;
    e->seq = le32(d + 8);
    e->sample_seq = le32(d + 12);
    t = (uint64_t)le32(d + 16) | ((uint64_t)le32(d + 20) << 32);
    e->t_us = (t >> 63) ? -(int64_t)(~t) - 1 : (int64_t)t; /* two's complement, portably */
    e->status = le32(d + 24);
    e->contact = d[28];
    e->conf_q15 = le16(d + 30);
    e->force_mN = (int32_t)le32(d + 32);
    e->x_um = (int32_t)le32(d + 36);
    e->y_um = (int32_t)le32(d + 40);
    return 0;
}

static uint64_t le64(const unsigned char *p)
{
    return (uint64_t)le32(p) | ((uint64_t)le32(p + 4) << 32);
}

/* 0 and the status record printed on stderr; -1 if the datagram is not a valid version-1
 * status record. */
static int status_record(const unsigned char *d, size_t n)
{
    static const char *const levels[4] = {"OK", "WARN", "ERROR", "STALE"};
    if (n != STATUS_SIZE || memcmp(d, "FBGS", 4) != 0) return -1;
    if (le16(d + 4) != 1 || le16(d + 6) != STATUS_SIZE) return -1;
    if (crc32(d, STATUS_CRC_OFFSET) != le32(d + STATUS_CRC_OFFSET)) return -1;
    fprintf(stderr, "status %lu: %s, %.1f Hz, received %llu, lost %llu, reconnects %lu, "
            "silent %lu ms\n", (unsigned long)le32(d + 8), levels[d[12] < 3 ? d[12] : 3],
            le32(d + 36) / 1000.0, (unsigned long long)le64(d + 16),
            (unsigned long long)le64(d + 24), (unsigned long)le32(d + 32),
            (unsigned long)le32(d + 40));
    return 0;
}

/* What publication counter seq means after last: FOLLOW_NEXT, a new estimate with *gap
 * datagrams missing before it (a forward step below 2^31); FOLLOW_DUPLICATE, the last counter
 * again (drop it); FOLLOW_RESTART, any other backward step: the publisher started again. */
enum { FOLLOW_NEXT, FOLLOW_DUPLICATE, FOLLOW_RESTART };

static int follow(int have_last, uint32_t last, uint32_t seq, uint32_t *gap)
{
    uint32_t step = seq - last;

    *gap = 0;
    if (!have_last) return FOLLOW_NEXT;
    if (step == 0u) return FOLLOW_DUPLICATE;
    if (step >= 0x80000000u) return FOLLOW_RESTART;
    *gap = step - 1u;
    return FOLLOW_NEXT;
}

int main(int argc, char **argv)
{
    struct sockaddr_in addr;
    unsigned char buf[256];
    long count, got = 0, bad = 0, missing = 0, duplicates = 0, restarts = 0, statuses = 0;
    uint32_t last = 0, gap;
    int have_last = 0, fd;

    if (argc < 3) {
        fprintf(stderr, "usage: %s ADDRESS PORT [COUNT]\n", argv[0]);
        return 2;
    }
    count = argc > 3 ? atol(argv[3]) : -1;
    fd = socket(AF_INET, SOCK_DGRAM, 0);
    if (fd < 0) {
        perror("socket");
        return 1;
    }
    {
        int size = 1 << 22; /* room for bursts: the publisher sends a batch at a time */
        setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &size, sizeof size);
    }
    memset(&addr, 0, sizeof addr);
    addr.sin_family = AF_INET;
    addr.sin_port = htons((uint16_t)atoi(argv[2]));
    if (inet_pton(AF_INET, argv[1], &addr.sin_addr) != 1 ||
        bind(fd, (struct sockaddr *)&addr, sizeof addr) != 0) {
        perror("bind");
        return 1;
    }
    fprintf(stderr, "listening\n");
    while (count < 0 || got < count) {
        fbg_estimate e;
        ssize_t n = recv(fd, buf, sizeof buf, 0);
        if (n < 0) {
            perror("recv");
            break;
        }
        if (decode(buf, (size_t)n, &e) != 0) {
            if (status_record(buf, (size_t)n) == 0)
                statuses++;
            else
                bad++;
            continue;
        }
        switch (follow(have_last, last, e.seq, &gap)) {
        case FOLLOW_DUPLICATE:
            duplicates++;
            continue;
        case FOLLOW_RESTART:
            restarts++;
            break;
        default:
            missing += (long)gap;
        }
        last = e.seq;
        have_last = 1;
        got++;
        printf("%lu,%lu,%lld,%lu,%u,%u,%ld,%ld,%ld\n", (unsigned long)e.seq,
               (unsigned long)e.sample_seq, (long long)e.t_us, (unsigned long)e.status,
               (unsigned)e.contact, (unsigned)e.conf_q15, (long)e.force_mN, (long)e.x_um,
               (long)e.y_um);
    }
    fflush(stdout);
    fprintf(stderr, "received %ld, bad %ld, missing %ld, duplicates %ld, restarts %ld, "
            "status records %ld\n", got, bad, missing, duplicates, restarts, statuses);
    close(fd);
    return 0;
}
