/* semihost.h - ARM semihosting over BKPT 0xAB (M profile); run QEMU with -semihosting.
 * QEMU 7.2 writes the console output (SYS_WRITE0) to its stderr. */
#ifndef FBG_FW_SEMIHOST_H
#define FBG_FW_SEMIHOST_H

#include <stdint.h>

static inline int semihost(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

/* Write a NUL-terminated string to the host console. */
static inline void sh_puts(const char *s) { semihost(0x04 /* SYS_WRITE0 */, s); }

/* Stop the emulator with this exit status (SYS_EXIT_EXTENDED); never returns. */
void sh_exit(int code) __attribute__((noreturn));
/* Print `label`, a decimal value and a newline. */
void sh_putu(const char *label, uint32_t v);
void sh_puti(const char *label, int32_t v);
/* Print " key=value" (no newline) - the firmware's result line is made of these. */
void sh_kv(const char *key, int32_t v);

#endif
