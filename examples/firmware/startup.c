/* startup.c - Cortex-M4 vector table and reset handler for QEMU mps2-an386 (no libc). */
#include <stdint.h>

#include "semihost.h"

extern uint32_t __stack_top, __data_load, __data_start, __data_end, __bss_start, __bss_end;
extern int main(void);

/* The copy loops would become memcpy/memset calls at -O2, which do not exist without libc. */
__attribute__((optimize("no-tree-loop-distribute-patterns"))) void Reset_Handler(void)
{
    uint32_t *s = &__data_load, *d = &__data_start;
    while (d < &__data_end)
        *d++ = *s++;
    for (d = &__bss_start; d < &__bss_end;)
        *d++ = 0;
#if defined(__ARM_FP)
    /* Hard-float build: grant full access to CP10/CP11 (the FPU) before any FP instruction. */
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
#endif
    sh_exit(main());
}

/* Any fault (e.g. an unaligned LDRD, or an M4 instruction on a core without it) ends the run
 * with a status no golden comparison can produce. */
static void Fault_Handler(void) { sh_exit(99); }

/* The vector table: the initial stack pointer, then 15 handlers (a struct so that the object
 * pointer and the function pointers keep their own types, as ISO C wants). */
typedef void (*fw_handler)(void);
struct fw_vectors {
    uint32_t *stack_top;
    fw_handler handlers[15];
};

__attribute__((section(".isr_vector"), used)) const struct fw_vectors vectors = {
    &__stack_top,
    {Reset_Handler, Fault_Handler /* NMI */, Fault_Handler /* HardFault */,
     Fault_Handler /* MemManage */, Fault_Handler /* BusFault */, Fault_Handler /* UsageFault */,
     0, 0, 0, 0, Fault_Handler /* SVC */, 0, 0, Fault_Handler /* PendSV */,
     Fault_Handler /* SysTick */},
};
