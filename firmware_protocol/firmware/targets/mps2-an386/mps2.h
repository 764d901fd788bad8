/*
 * mps2.h - the few registers of the Arm MPS2 AN386 FPGA image (Cortex-M4) this target uses,
 * as qemu-system-arm -M mps2-an386 models them: CMSDK APB UART0 and timer 0, the NVIC and
 * the SCB. Register layouts: Arm "Cortex-M System Design Kit Technical Reference Manual"
 * (DDI 0479) and the ARMv7-M Architecture Reference Manual.
 */
#ifndef SPIEL_MPS2_H
#define SPIEL_MPS2_H

#include <stdint.h>

#define MPS2_SYSCLK_HZ 25000000u /* the AN386 system clock that drives the APB peripherals */

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))

/* CMSDK APB UART0 */
#define UART0_BASE 0x40004000u
#define UART_DATA(b) REG32((b) + 0x000u)
#define UART_STATE(b) REG32((b) + 0x004u)
#define UART_CTRL(b) REG32((b) + 0x008u)
#define UART_INTSTATUS(b) REG32((b) + 0x00Cu) /* read: pending; write 1: clear */
#define UART_BAUDDIV(b) REG32((b) + 0x010u)
#define UART_STATE_TXFULL 0x1u
#define UART_STATE_RXFULL 0x2u
#define UART_STATE_TXOVR 0x4u
#define UART_STATE_RXOVR 0x8u
#define UART_CTRL_TXEN 0x1u
#define UART_CTRL_RXEN 0x2u
#define UART_CTRL_TXINTEN 0x4u
#define UART_CTRL_RXINTEN 0x8u
#define UART_INT_TX 0x1u
#define UART_INT_RX 0x2u
#define UART0_RX_IRQ 0u
#define UART0_TX_IRQ 1u

/* CMSDK APB timer 0: a 32-bit down counter at the system clock */
#define TIMER0_BASE 0x40000000u
#define TIMER_CTRL(b) REG32((b) + 0x000u)
#define TIMER_VALUE(b) REG32((b) + 0x004u)
#define TIMER_RELOAD(b) REG32((b) + 0x008u)
#define TIMER_INTSTATUS(b) REG32((b) + 0x00Cu)
#define TIMER_CTRL_EN 0x1u
#define TIMER_CTRL_IRQEN 0x8u
#define TIMER0_IRQ 8u
#define TIMER1_BASE 0x40001000u /* the idle wake-up */
#define TIMER1_IRQ 9u

/* The 16 MB PSRAM at 0x21000000 is the machine's main RAM in qemu, so a
 * memory-backend-file (share=on) keeps it in a host file across kills and restarts:
 * this target puts its emulated flash there and links nothing else into it. */
#define PSRAM_BASE 0x21000000u

/* What lives in that persistent PSRAM (offsets), NOR-like (nor_mps2.c): erased 0xFF, a write
 * only clears bits, erased in 4 KiB sectors. */
#define NOR_SECTOR 0x1000u
#define CFG_FLASH_OFF 0x000000u  /* 64 KiB: the config store (hal_flash_*) */
#define CFG_FLASH_SIZE 0x10000u
#define BOOT_REC_OFF 0x010000u   /* two sectors: the boot record's two 16-byte copies */
#define SLOT0_OFF 0x100000u      /* image slot 0; slot 1 follows */
#define IMAGE_SLOT_SIZE 0x100000u /* 1 MiB per slot, the 96-byte image header included */
#define FI_OFF 0x00F00000u       /* the power-cut mailbox of the tests (nor_mps2.c) */
#define SEED_OFF 0x00F01000u     /* a plain word carried across boots: hal_random's state */

/* Where every application image runs (RAM load): ZBT SSRAM1 above the boot stage. The boot
 * stage copies the chosen slot's body here; qemu's loader puts the built-in (factory) image
 * here at every reset. */
#define EXEC_BASE 0x00010000u
#define EXEC_SIZE (IMAGE_SLOT_SIZE - 96u)
/* The execution region is flash of its own here (SSRAM1 plays the MCU's internal flash): the
 * boot stage copies an image into it flash to flash (boot_install: per sector, in program
 * units of IMAGE_UNIT), with the installed image's header in the sector below EXEC_BASE,
 * written last. qemu's loader puts the built-in image and a zeroed header sector (no image
 * header: "the built-in image is installed") back at every reset. */
#define EXEC_HDR_ADDR (EXEC_BASE - NOR_SECTOR)
#define IMAGE_UNIT 8u            /* program unit of the image areas (ECC flash) */
/* CMSDK APB watchdog (qemu: the reset after two expiries without INTCLR, at 25 MHz) */
#define WDOG_BASE 0x40008000u
#define WDOG_LOAD REG32(WDOG_BASE + 0x000u)
#define WDOG_CTRL REG32(WDOG_BASE + 0x008u)
#define WDOG_INTCLR REG32(WDOG_BASE + 0x00Cu)
#define WDOG_LOCK REG32(WDOG_BASE + 0xC00u)
#define WDOG_UNLOCK 0x1ACCE551u
#define WDOG_CTRL_RESEN 0x2u
#define APP_RAM_BASE 0x20000000u /* the application's data and stack: 2 MiB */
#define APP_RAM_SIZE 0x00200000u
/* The boot stage tells the application which slot it copied: two words at the top of SSRAM2/3,
 * outside both programs' RAM. */
#define HANDOFF_ADDR 0x203FFF00u
#define HANDOFF_MAGIC 0x4F464E48u /* "HNFO" */
#define HANDOFF_FACTORY 0xFFFFFFFFu

/* NOR rules at an absolute address (the PSRAM, or SSRAM1's execution region, the MCU's
 * internal flash of this model); each call is one operation of the power-cut hook */
int flash_erase_at(uint32_t addr, uint32_t len);
int flash_write_at(uint32_t addr, const uint8_t *data, uint32_t len);
void flash_read_at(uint32_t addr, uint8_t *data, uint32_t len);
int nor_erase(uint32_t off, uint32_t len);                     /* 0 ok, -1 failed */
int nor_write(uint32_t off, const uint8_t *data, uint32_t len); /* 0 ok, -1 failed */
void nor_read(uint32_t off, uint8_t *data, uint32_t len);

/* System control block and NVIC */
#define SCB_AIRCR REG32(0xE000ED0Cu)
#define SCB_CPACR REG32(0xE000ED88u)
#define SCB_VTOR REG32(0xE000ED08u)
#define AIRCR_VECTKEY 0x05FA0000u
#define AIRCR_SYSRESETREQ 0x4u
#define NVIC_ISER0 REG32(0xE000E100u)
#define NVIC_ICER0 REG32(0xE000E180u)

static inline void irq_disable(void) { __asm volatile("cpsid i" ::: "memory"); }
static inline void irq_enable(void) { __asm volatile("cpsie i" ::: "memory"); }
static inline uint32_t irq_save(void)
{
    uint32_t primask;
    __asm volatile("mrs %0, primask\n cpsid i" : "=r"(primask)::"memory");
    return primask;
}
static inline void irq_restore(uint32_t primask)
{
    __asm volatile("msr primask, %0" ::"r"(primask) : "memory");
}
static inline void dsb(void) { __asm volatile("dsb 0xF" ::: "memory"); }
static inline void isb(void) { __asm volatile("isb 0xF" ::: "memory"); }

#endif /* SPIEL_MPS2_H */
