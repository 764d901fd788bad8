/*
 * rp2040_board.h - what the RP2040 target's own files share (not a HAL: spiel_hal.h is).
 *
 * Flash (the Pico's 2 MiB W25Q16 QSPI NOR, read through XIP at 0x10000000), all of it 4 KiB
 * sectors, programmed in 256-byte pages (flash_rp2040.c pads a page with 0xFF, which NOR
 * programming leaves unchanged, so any byte range can be programmed once):
 *   0x000000  64 KiB   boot2 (256 B) and the boot stage (boot_rp2040.c, rp2040-boot.ld),
 *                      never updated
 *   0x010000  512 KiB  the execution region (SPIEL_IMAGE_EXEC): the installed image's header
 *                      in its first sector, the application from 0x011000, where it is linked
 *                      and runs in place (rp2040-app.ld)
 *   0x090000  512 KiB  image slot 0 (header + body)
 *   0x110000  512 KiB  image slot 1
 *   0x190000  8 KiB    the boot record's two copies (SPIEL_IMAGE_RECORD)
 *   0x1F0000  64 KiB   the config store (hal_flash_*)
 * The UF2 holds the boot stage, the application packed into slot 0, and the same image already
 * installed in the execution region (so the first start copies nothing).
 */
#ifndef SPIEL_RP2040_BOARD_H
#define SPIEL_RP2040_BOARD_H

#include <stdint.h>

#include "hardware/regs/intctrl.h" /* isr_usbctrl is isr_irq5 */

/* The USB id the host looks for by default (spiel_edge/link/usb_ids.py BOARD_USB_IDS, the udev
 * rule of `spiel-edge service`): pid.codes' test id 1209:0001, fine for a prototype; a product
 * takes an id of its own and sets SPIEL_USB_IDS on the host (docs/build-a-board.md). */
#define RP2040_USB_VID 0x1209u
#define RP2040_USB_PID 0x0001u

#define RP2040_FLASH_BYTES (2u * 1024u * 1024u)
#define RP2040_SECTOR 4096u
#define RP2040_PAGE 256u
#define RP2040_CFG_SIZE 0x10000u
#define RP2040_CFG_OFF (RP2040_FLASH_BYTES - RP2040_CFG_SIZE)
#define RP2040_BOOT_SIZE 0x10000u /* what the data areas never reach */
#define RP2040_EXEC_OFF 0x010000u
#define RP2040_AREA_SIZE 0x080000u
#define RP2040_SLOT0_OFF 0x090000u
#define RP2040_RECORD_OFF 0x190000u
/* The boot stage tells the application which slot it installed: two watchdog scratch words
 * (kept across a watchdog reset, rewritten at every boot). Scratch 3 is hal_random's. */
#define RP2040_HANDOFF_MAGIC 0x4F464E48u /* "HNFO" */

/* flash_rp2040.c: offsets from the start of the flash. 0 ok, -1 bad range. */
int rp2040_flash_erase(uint32_t off, uint32_t len);
int rp2040_flash_program(uint32_t off, const uint8_t *data, uint32_t len);
void rp2040_flash_read(uint32_t off, uint8_t *data, uint32_t len);
/* The board's serial number (the flash's unique id in hex; a fixed text in the emulator). */
const char *rp2040_serial(void);

/* image_rp2040.c: the running image's version text (its header): 0, or -1 */
int rp2040_image_version(char version[17]);
/* clocks_rp2040.c: crystal, clk_sys 125 MHz, clk_usb 48 MHz, the 1 MHz tick */
void rp2040_clocks_start(void);
/* hal_rp2040.c */
void rp2040_hal_init(void);
void rp2040_wait(uint32_t us); /* sleep until USB activity or us microseconds */
void isr_timer0(void);
#ifndef RP2040_SONICLIB
#define RP2040_SONICLIB 0
#endif
#if RP2040_SONICLIB
/* sensor/sensor_soniclib.c: start the CH101 group, fill the board info. 0 ok, -1 none. */
#include "spiel_hal.h"
int rp2040_sensor_init(hal_board_info_t *board);
#endif
/* usb_rp2040.c */
void isr_usbctrl(void);

#endif
