/*
 * tb_target_semihost.c - the exit and the fault reports of the target images over semihosting
 * (startup_m4.c calls them): no stdio, so the minimal image links without newlib's.
 */
#include <stdint.h>

static int semihost(int op, const void *arg)
{
    register int r0 __asm("r0") = op;
    register const void *r1 __asm("r1") = arg;
    __asm volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

/* the harness flushes its stdout here (a no-op in the minimal image) */
__attribute__((weak)) void tb_target_flush(void) {}

void tb_target_exit(int code)
{
    tb_target_flush();
    /* SYS_EXIT: ADP_Stopped_ApplicationExit ends QEMU with status 0, any other reason with 1 */
    semihost(0x18, (const void *)(uintptr_t)(code == 0 ? 0x20026 : 0x20023));
    for (;;) {
    }
}

void tb_target_fault(const char *what)
{
    semihost(0x04, "tb_target: fault: ");
    semihost(0x04, what);
    semihost(0x04, "\n");
    semihost(0x18, (const void *)(uintptr_t)0x20023);
    for (;;) {
    }
}

/* a fault with the faulting instruction's address (the stacked pc) and the fault status */
void tb_target_fault_at(const char *what, const uint32_t *frame)
{
    static char msg[96];
    static const char hex[] = "0123456789abcdef";
    uint32_t vals[2], v;
    int i, k, n = 0;
    vals[0] = frame[6];
    vals[1] = *(volatile uint32_t *)0xE000ED28u; /* CFSR */
    for (i = 0; what[i] && n < 40; i++) msg[n++] = what[i];
    for (k = 0; k < 2; k++) {
        const char *lab = k == 0 ? " pc=0x" : " cfsr=0x";
        for (i = 0; lab[i]; i++) msg[n++] = lab[i];
        for (i = 7; i >= 0; i--) {
            v = (vals[k] >> (4 * i)) & 0xFu;
            msg[n++] = hex[v];
        }
    }
    msg[n] = 0;
    tb_target_fault(msg);
}
