/*
 * tests/m7/startup.c - bare-metal start of the controller firmware on qemu's mps2-an500 (Cortex-M7):
 * vector table, reset (FPU on, .data copied, .bss zeroed, main, exit) and the few ARM semihosting
 * calls the firmware uses (console output, exit with a status). No OS, no heap.
 */
#include <stdint.h>

#include "m7_board.h"

extern uint32_t __data_load, __data_start, __data_end, __bss_start, __bss_end, __stack_top;
int main(void);
void m7_reset(void);

static void m7_fault(void)
{
    m7_puts("m7: FAULT (hard fault or unexpected exception)\n");
    m7_exit(3);
}

/* SysTick: a fault unless the firmware defines it (the profiling build samples the PC there) */
void m7_systick(void) __attribute__((weak, alias("m7_fault_handler")));
void m7_fault_handler(void);
void m7_fault_handler(void)
{
    m7_fault();
}

/* initial SP, then reset, NMI, HardFault, MemManage, BusFault, UsageFault, ..., SysTick (15) */
typedef struct {
    uint32_t *initial_sp;
    void (*handler[15])(void);
} m7_vector_table;
__attribute__((section(".vectors"), used)) static const m7_vector_table vectors = {
    &__stack_top,
    {m7_reset, m7_fault, m7_fault, m7_fault, m7_fault, m7_fault, 0, 0, 0, 0, 0, 0, 0, 0, m7_systick}};

static uintptr_t semihost(uintptr_t op, const void *arg)
{
    register uintptr_t r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void m7_puts(const char *s)
{
    semihost(0x04u, s); /* SYS_WRITE0 */
}

void m7_exit(int code)
{
    /* SYS_EXIT_EXTENDED: qemu exits with `code` */
    uintptr_t block[2] = {0x20026u /* ADP_Stopped_ApplicationExit */, (uintptr_t)code};
    semihost(0x20u, block);
    for (;;) {
    }
}

void m7_reset(void)
{
    volatile uint32_t *src = &__data_load, *dst = &__data_start;
    /* CP10, CP11 full access: the FPU before any floating-point instruction */
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    while (dst < &__data_end) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start; dst < &__bss_end; ++dst) {
        *dst = 0u;
    }
    m7_exit(main());
}
