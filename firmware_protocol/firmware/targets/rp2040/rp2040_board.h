/*
 * rp2040_board.h - what the RP2040 target's own files share (not a HAL: spiel_hal.h is).
 *
 * Flash (the Pico's 2 MiB W25Q16 QSPI NOR, read through XIP at 0x10000000):
 *   0x000000  boot2 (256 B) and the program, linked to run in place (rp2040.ld)
 *   0x1F0000  64 KiB: the config store (hal_flash_*), 16 sectors of 4 KiB
 * Erase: 4 KiB sectors; program: any bytes, in 256-byte pages (flash_rp2040.c pads a page with
 * 0xFF, which NOR programming leaves unchanged).
 */
#ifndef SPIEL_RP2040_BOARD_H
#define SPIEL_RP2040_BOARD_H

#include <stdint.h>

#include "hardware/regs/intctrl.h" /* isr_usbctrl is isr_irq5 */

/* Raspberry Pi's vendor id with the Pico SDK's CDC product id: fine for a prototype; a product
 * asks Raspberry Pi for a product id of its own (docs/build-a-board.md). */
#define RP2040_USB_VID 0x2E8Au
#define RP2040_USB_PID 0x000Au

#define RP2040_FLASH_BYTES (2u * 1024u * 1024u)
#define RP2040_SECTOR 4096u
#define RP2040_PAGE 256u
#define RP2040_CFG_SIZE 0x10000u
#define RP2040_CFG_OFF (RP2040_FLASH_BYTES - RP2040_CFG_SIZE)

/* flash_rp2040.c: offsets from the start of the flash. 0 ok, -1 bad range. */
int rp2040_flash_erase(uint32_t off, uint32_t len);
int rp2040_flash_program(uint32_t off, const uint8_t *data, uint32_t len);
void rp2040_flash_read(uint32_t off, uint8_t *data, uint32_t len);
/* The board's serial number (the flash's unique id in hex; a fixed text in the emulator). */
const char *rp2040_serial(void);

/* hal_rp2040.c */
void rp2040_hal_init(void);
void rp2040_wait(uint32_t us); /* sleep until USB activity or us microseconds */
void isr_timer0(void);
/* usb_rp2040.c */
void isr_usbctrl(void);

#endif
