/*
 * Minimal Cortex-M4F start-up for the thermbench target harness: the vector table, a reset
 * handler that copies .data, zeroes .bss, enables the FPU and calls main; the stack painting that
 * measures the runtime's depth, and fault handlers that report over semihosting and stop.
 */
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _sstack, _estack;
extern int main(void);
extern void tb_target_exit(int code);
extern void tb_target_fault(const char *what);

#define STACK_PAINT 0xA5A5A5A5u

void Reset_Handler(void);
static void NMI_Handler(void) { tb_target_fault("NMI"); }
extern void tb_target_fault_at(const char *what, const uint32_t *frame);
/* the stacked exception frame (r0-r3, r12, lr, pc, xpsr) of the main or process stack */
__attribute__((naked)) static void HardFault_Handler(void)
{
    __asm volatile("tst lr, #4\n\t"
                   "ite eq\n\t"
                   "mrseq r1, msp\n\t"
                   "mrsne r1, psp\n\t"
                   "ldr r0, =tb_hardfault_name\n\t"
                   "b tb_target_fault_at\n\t");
}
const char tb_hardfault_name[] = "HardFault";
static void MemManage_Handler(void) { tb_target_fault("MemManage"); }
static void BusFault_Handler(void) { tb_target_fault("BusFault"); }
static void UsageFault_Handler(void) { tb_target_fault("UsageFault"); }
static void Default_Handler(void) { tb_target_fault("unexpected interrupt"); }

__attribute__((section(".isr_vector"), used)) void (*const tb_vectors[16])(void) = {
    (void (*)(void))(&_estack), Reset_Handler, NMI_Handler, HardFault_Handler, MemManage_Handler,
    BusFault_Handler, UsageFault_Handler, 0, 0, 0, 0, Default_Handler, Default_Handler, 0,
    Default_Handler, Default_Handler,
};

void Reset_Handler(void)
{
    uint32_t *src = &_sidata, *dst;
    for (dst = &_sdata; dst < &_edata;) *dst++ = *src++;
    for (dst = &_sbss; dst < &_ebss;) *dst++ = 0;
    /* CP10 and CP11 full access: the FPU (fpv4-sp-d16) */
    *(volatile uint32_t *)0xE000ED88u |= (0xFu << 20);
    __asm volatile("dsb\n\tisb");
    tb_target_exit(main());
}

/* paint the stack below the caller's frame again; tb_target_stack_below(sp) then tells how deep
   the calls in between went below that sp (the runtime's own use, without the harness's) */
void tb_target_stack_repaint(void)
{
    uint32_t *dst;
    volatile uint32_t *sp_now;
    __asm volatile("mov %0, sp" : "=r"(sp_now));
    for (dst = &_sstack; dst < (uint32_t *)sp_now - 16; dst++) *dst = STACK_PAINT;
}

uint32_t tb_target_stack_below(uint32_t sp)
{
    uint32_t *p = &_sstack;
    while (p < &_estack && *p == STACK_PAINT) p++;
    return (uint32_t)p < sp ? sp - (uint32_t)p : 0u;
}
