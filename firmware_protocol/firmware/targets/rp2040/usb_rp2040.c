/*
 * usb_rp2040.c - TinyUSB's side of the RP2040 target: the USB descriptors (one CDC-ACM
 * interface pair), the two SDK interrupt calls TinyUSB's RP2040 driver makes (one handler, the
 * USB controller's, dispatched from the vector table in startup_rp2040.c instead of the SDK's
 * RAM vector table and handler chains) and the SDK's panic().
 */
#include <string.h>

#include "hardware/irq.h"
#include "hardware/sync.h"
#include "hardware/watchdog.h"
#include "rp2040_board.h"
#include "tusb.h"

/* ---- interrupts ------------------------------------------------------------------------ */

static irq_handler_t usb_handler;

void isr_usbctrl(void)
{
    if (usb_handler != NULL) {
        usb_handler();
    }
}

void irq_add_shared_handler(uint num, irq_handler_t handler, uint8_t order_priority)
{
    (void)order_priority;
    if (num == USBCTRL_IRQ) {
        usb_handler = handler;
    }
}

void irq_remove_handler(uint num, irq_handler_t handler)
{
    if (num == USBCTRL_IRQ && usb_handler == handler) {
        usb_handler = NULL;
    }
}

void irq_set_enabled(uint num, bool enabled)
{
    uint32_t bit = 1u << num;
    if (enabled) {
        nvic_hw->icpr = bit;
        nvic_hw->iser = bit;
    } else {
        nvic_hw->icer = bit;
    }
}

void panic(const char *fmt, ...)
{
    (void)fmt; /* no console on this board: restart rather than hang */
    (void)save_and_disable_interrupts();
    watchdog_reboot(0, 0, 0);
    for (;;) {
        __wfi();
    }
}

void hard_assertion_failure(void)
{
    panic("");
}

/* ---- descriptors ----------------------------------------------------------------------- */

enum { ITF_CDC, ITF_CDC_DATA, ITF_COUNT };
enum { STR_LANG, STR_MANUFACTURER, STR_PRODUCT, STR_SERIAL, STR_CDC };
#define EP_NOTIF 0x81
#define EP_OUT 0x02
#define EP_IN 0x82
#define CONFIG_LEN (TUD_CONFIG_DESC_LEN + TUD_CDC_DESC_LEN)

static const tusb_desc_device_t device_desc = {
    .bLength = sizeof(tusb_desc_device_t),
    .bDescriptorType = TUSB_DESC_DEVICE,
    .bcdUSB = 0x0200,
    .bDeviceClass = TUSB_CLASS_MISC, /* interface association: the CDC pair is one function */
    .bDeviceSubClass = MISC_SUBCLASS_COMMON,
    .bDeviceProtocol = MISC_PROTOCOL_IAD,
    .bMaxPacketSize0 = CFG_TUD_ENDPOINT0_SIZE,
    .idVendor = RP2040_USB_VID,
    .idProduct = RP2040_USB_PID,
    .bcdDevice = 0x0100,
    .iManufacturer = STR_MANUFACTURER,
    .iProduct = STR_PRODUCT,
    .iSerialNumber = STR_SERIAL,
    .bNumConfigurations = 1,
};

static const uint8_t config_desc[] = {
    TUD_CONFIG_DESCRIPTOR(1, ITF_COUNT, 0, CONFIG_LEN, 0x00, 100),
    TUD_CDC_DESCRIPTOR(ITF_CDC, STR_CDC, EP_NOTIF, 8, EP_OUT, EP_IN, 64),
};

uint8_t const *tud_descriptor_device_cb(void)
{
    return (uint8_t const *)&device_desc;
}

uint8_t const *tud_descriptor_configuration_cb(uint8_t index)
{
    (void)index;
    return config_desc;
}

uint16_t const *tud_descriptor_string_cb(uint8_t index, uint16_t langid)
{
    static uint16_t desc[1 + 32];
    const char *text;
    size_t n, i;
    (void)langid;
    switch (index) {
    case STR_LANG:
        desc[1] = 0x0409; /* English (US) */
        desc[0] = (uint16_t)((TUSB_DESC_STRING << 8) | 4u);
        return desc;
    case STR_MANUFACTURER: text = "spiel-edge"; break;
    case STR_PRODUCT: text = "spiel-edge RP2040 board"; break;
    case STR_SERIAL: text = rp2040_serial(); break;
    case STR_CDC: text = "spiel-edge CDC"; break;
    default: return NULL;
    }
    n = strlen(text);
    if (n > 32) {
        n = 32;
    }
    for (i = 0; i < n; i++) {
        desc[1 + i] = (uint8_t)text[i];
    }
    desc[0] = (uint16_t)((TUSB_DESC_STRING << 8) | (2u * n + 2u));
    return desc;
}
