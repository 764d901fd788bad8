/*
 * nor_mps2.c - the persistent memory of the mps2-an386 target: NOR-like flash (erase sets
 * 0xFF in whole sectors, a write only clears bits) in the PSRAM, which qemu backs with a host
 * file, so what was written survives a kill of qemu. The config store, the boot record and the
 * two image slots all live here (mps2.h); the boot stage and the application both use it.
 *
 * Power-cut hook for the tests (tests/firmware): a mailbox in the PSRAM, which the test writes
 * into the host file before booting the board. When armed, the n-th flash operation (erase or
 * write, 0-based, counted in the mailbox from when it was armed, so across resets and from the
 * boot stage to the application) does only its first half and then the board stops dead
 * (mode CUT), or fails (mode FAIL). Fires once. Unarmed on a real board.
 */
#include "mps2.h"

#define FI_BASE (PSRAM_BASE + FI_OFF)
#define FI_MAGIC REG32(FI_BASE + 0u) /* "SPFI" */
#define FI_MODE REG32(FI_BASE + 4u)  /* 1 CUT, 2 FAIL */
#define FI_AT REG32(FI_BASE + 8u)    /* operation number, 0-based */
#define FI_OPS REG32(FI_BASE + 12u)  /* operations so far (written by the board) */
#define FI_FIRED REG32(FI_BASE + 16u) /* 1 once the cut or failure happened */
#define FI_MAGIC_VALUE 0x49465053u
#define FI_CUT 1u
#define FI_FAIL 2u

/* Count one operation; 1: do it whole, 0: cut it in half and die, -1: fail it. */
static int nor_op(void)
{
    uint32_t op;
    if (FI_MAGIC != FI_MAGIC_VALUE || FI_FIRED) {
        return 1;
    }
    op = FI_OPS;
    FI_OPS = op + 1u;
    if (op != FI_AT) {
        return 1;
    }
    if (FI_MODE == FI_FAIL) {
        FI_FIRED = 1u;
        return -1;
    }
    return FI_MODE == FI_CUT ? 0 : 1;
}

static void nor_die(void)
{
    FI_FIRED = 1u;
    irq_disable();
    NVIC_ICER0 = 0xFFFFFFFFu; /* nothing may pend and wake the WFI again */
    for (;;) {
        __asm volatile("wfi");
    }
}

int flash_erase_at(uint32_t addr, uint32_t len)
{
    uint32_t i, n;
    int op;
    if (addr % NOR_SECTOR != 0 || len % NOR_SECTOR != 0) {
        return -1;
    }
    op = nor_op();
    if (op < 0) {
        return -1;
    }
    n = op ? len : len / 2u;
    for (i = 0; i < n; i += 4u) { /* aligned words: a 1 MiB slot in a few ms of qemu */
        REG32(addr + i) = 0xFFFFFFFFu;
    }
    if (!op) {
        nor_die();
    }
    return 0;
}

int flash_write_at(uint32_t addr, const uint8_t *data, uint32_t len)
{
    volatile uint8_t *p = (volatile uint8_t *)(uintptr_t)addr;
    uint32_t i;
    int op = nor_op();
    if (op < 0) {
        return -1;
    }
    for (i = 0; i < (op ? len : len / 2u); i++) {
        p[i] &= data[i]; /* NOR: programming only clears bits */
    }
    if (!op) {
        nor_die();
    }
    return 0;
}

void flash_read_at(uint32_t addr, uint8_t *data, uint32_t len)
{
    const volatile uint8_t *p = (const volatile uint8_t *)(uintptr_t)addr;
    uint32_t i;
    for (i = 0; i < len; i++) {
        data[i] = p[i];
    }
}

int nor_erase(uint32_t off, uint32_t len)
{
    return flash_erase_at(PSRAM_BASE + off, len);
}

int nor_write(uint32_t off, const uint8_t *data, uint32_t len)
{
    return flash_write_at(PSRAM_BASE + off, data, len);
}

void nor_read(uint32_t off, uint8_t *data, uint32_t len)
{
    flash_read_at(PSRAM_BASE + off, data, len);
}
