/* tusb_config.h - TinyUSB for the spiel-edge RP2040 target: one CDC-ACM device on the RP2040's
 * full-speed controller, no RTOS (tud_task() runs in the main loop). */
#ifndef SPIEL_RP2040_TUSB_CONFIG_H
#define SPIEL_RP2040_TUSB_CONFIG_H

#define CFG_TUSB_MCU OPT_MCU_RP2040
#define CFG_TUSB_OS OPT_OS_NONE
#define CFG_TUSB_RHPORT0_MODE OPT_MODE_DEVICE
#define CFG_TUD_ENABLED 1
#define CFG_TUD_ENDPOINT0_SIZE 64
#define CFG_TUD_CDC 1
/* one acquisition's frames (4 x 64 samples: about 680 B) fit the transmit FIFO at once */
#define CFG_TUD_CDC_RX_BUFSIZE 1024
#define CFG_TUD_CDC_TX_BUFSIZE 2048
#define CFG_TUD_CDC_EP_BUFSIZE 64
/* The RP2040-E5 enumeration fix (B0/B1 silicon only) needs the SDK's GPIO and alarm layers;
 * boards sold since 2021 carry B2 silicon, so it is left out (vendor/README.md). */
#define TUD_OPT_RP2040_USB_DEVICE_ENUMERATION_FIX 0

#endif
