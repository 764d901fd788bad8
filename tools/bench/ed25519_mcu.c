/* ed25519_mcu.c - one crypto_ed25519_check() of a signed image header on a bare Cortex-M0
 * (qemu -M microbit, nRF51: ARMv6-M, the Cortex-M0+'s instruction set) or Cortex-M4
 * (qemu -M mps2-an386), timed by the board's timer; prints "ok=R ticks=T" on the UART.
 * Under qemu -icount shift=0 every instruction advances the virtual clock by 1 ns, so T ticks
 * of a timer at F Hz are T * 1e9 / F instructions. Built and run by tools/bench/bench_ed25519.py,
 * which writes bench_vec.h (public key, 96-byte header, signature). No libc, no interrupts. */
#include <stdint.h>

#include "bench_vec.h"
#include "monocypher-ed25519.h"

#define REG(a) (*(volatile uint32_t *)(uintptr_t)(a))

#if defined(BENCH_MICROBIT) /* nRF51822: TIMER0 at 16 MHz, UART0 */
static void timer_start(void)
{
    REG(0x40008504u) = 0; /* MODE timer */
    REG(0x40008508u) = 3; /* BITMODE 32 */
    REG(0x40008510u) = 0; /* PRESCALER: 16 MHz */
    REG(0x40008000u) = 1; /* TASKS_START */
}
static uint32_t timer_now(void)
{
    REG(0x40008040u) = 1; /* TASKS_CAPTURE[0] */
    return REG(0x40008540u);
}
static void uart_init(void)
{
    REG(0x40002500u) = 4; /* ENABLE */
    REG(0x40002008u) = 1; /* TASKS_STARTTX */
}
static void uart_put(char c)
{
    REG(0x4000251Cu) = (uint8_t)c;
    while (!REG(0x4000211Cu)) { /* EVENTS_TXDRDY */
    }
    REG(0x4000211Cu) = 0;
}
#else /* MPS2 AN386: CMSDK timer 0 (down counter at 25 MHz), CMSDK UART0 */
static void timer_start(void)
{
    REG(0x40000008u) = 0xFFFFFFFFu; /* RELOAD */
    REG(0x40000004u) = 0xFFFFFFFFu; /* VALUE */
    REG(0x40000000u) = 1;           /* CTRL: enable */
}
static uint32_t timer_now(void)
{
    return 0xFFFFFFFFu - REG(0x40000004u);
}
static void uart_init(void)
{
    REG(0x40004010u) = 16; /* BAUDDIV */
    REG(0x40004008u) = 1;  /* CTRL: TXEN */
}
static void uart_put(char c)
{
    while (REG(0x40004004u) & 1u) { /* STATE: TXFULL */
    }
    REG(0x40004000u) = (uint8_t)c;
}
#endif

static void put_u32(uint32_t v)
{
    char d[10];
    int n = 0;
    do {
        d[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (n) {
        uart_put(d[--n]);
    }
}

static void put_s(const char *s)
{
    while (*s) {
        uart_put(*s++);
    }
}

void reset_handler(void);
extern uint32_t _estack;
__attribute__((section(".vectors"), used)) const uintptr_t vectors[2] = {
    (uintptr_t)&_estack, (uintptr_t)reset_handler};

void reset_handler(void)
{
    uint32_t t0, t1;
    int ok, bad;
    uint8_t flipped[64];
    unsigned i;
    uart_init();
    timer_start();
    t0 = timer_now();
    ok = crypto_ed25519_check(bench_sig, bench_pk, bench_msg, sizeof bench_msg);
    t1 = timer_now();
    for (i = 0; i < 64; i++) {
        flipped[i] = bench_sig[i];
    }
    flipped[40] ^= 1;
    bad = crypto_ed25519_check(flipped, bench_pk, bench_msg, sizeof bench_msg);
    put_s(ok == 0 && bad != 0 ? "ok=1 ticks=" : "ok=0 ticks=");
    put_u32(t1 - t0);
    put_s("\n");
    for (;;) {
    }
}
