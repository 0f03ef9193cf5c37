/* semihost.c - minimal semihosting console and exit (no libc). */
#include "semihost.h"

void sh_exit(int code)
{
    /* SYS_EXIT_EXTENDED (0x20) with {ADP_Stopped_ApplicationExit, code}: QEMU exits with `code`. */
    uint32_t blk[2] = {0x20026u, (uint32_t)code};
    semihost(0x20, blk);
    for (;;) {
    }
}

static char *utoa10(uint32_t v, char *end)
{
    *--end = 0;
    do {
        *--end = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    return end;
}

static char *itoa10(int32_t v, char *end)
{
    /* Negate in unsigned arithmetic: INT32_MIN has no positive int32 counterpart. */
    char *p = utoa10(v < 0 ? 0u - (uint32_t)v : (uint32_t)v, end);
    if (v < 0)
        *--p = '-';
    return p;
}

void sh_putu(const char *label, uint32_t v)
{
    char b[16];
    sh_puts(label);
    sh_puts(utoa10(v, b + sizeof b));
    sh_puts("\n");
}

void sh_puti(const char *label, int32_t v)
{
    char b[16];
    sh_puts(label);
    sh_puts(itoa10(v, b + sizeof b));
    sh_puts("\n");
}

void sh_kv(const char *key, int32_t v)
{
    char b[16];
    sh_puts(" ");
    sh_puts(key);
    sh_puts("=");
    sh_puts(itoa10(v, b + sizeof b));
}
