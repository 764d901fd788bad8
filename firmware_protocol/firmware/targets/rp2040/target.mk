# targets/rp2040/target.mk - the Raspberry Pi Pico (RP2040) images, included by ../../Makefile for
# TARGET=rp2040. make only (no CMake, no picotool), offline: the Pico SDK and TinyUSB files it
# uses are vendored under vendor/ (vendor/README.md). Outputs under $(BUILD):
#   firmware.uf2      what a person drags onto a Pico in BOOTSEL mode: the boot stage, the
#                     application packed as the image in slot 0, and installed in the execution
#                     region (rp2040_board.h)
#   app.bin           the application alone (linked for the execution region): the BODY that
#                     `spiel-edge firmware pack --target rp2040` wraps for `firmware update`
#   boot.elf, app.elf the two programs; boot2.S: boot2 padded to 252 bytes + its CRC-32
#   *-emu.*           the same with the emulator's flash path (flash_rp2040.c): what
#                     run-emulated.sh runs in rp2040js (firmware-emu.uf2); never for a board
#   obj/*.su          -fstack-usage of every file (make TARGET=rp2040 stack)
# Signed images (PROTOCOL.md 14.6), as on mps2: core/verify.c and the vendored Ed25519 verifier
# (vendor/monocypher) are in the boot stage (it starts only a slot signed by FW_KEY) and in the
# application (FW_VERIFY). The slot-0 image of firmware.uf2 is signed by FW_SIGN_KEY, the private
# half of FW_KEY (default: FW_KEY with .key for .pub, so keys/dev.key for the development key;
# RELEASE=1 refuses the development key), security counter RP_SECURITY_COUNTER (default 0).
RP_DIR := targets/rp2040
# The CH101/CH201 sensor layer over TDK SonicLib (sensor/): built against the user's checkout
# of github.com/tdk-invn-oss/ultrasonic.soniclib, never vendored (its licence restricts it to
# TDK sensors): make TARGET=rp2040 SONICLIB_DIR=/path/to/ultrasonic.soniclib. Its images go
# to build/rp2040-soniclib (firmware.uf2, app.bin; no emulator image: rp2040js has no sensor).
ifdef SONICLIB_DIR
ifeq ($(wildcard $(SONICLIB_DIR)/invn/soniclib/soniclib.h),)
$(error rp2040: SONICLIB_DIR=$(SONICLIB_DIR) holds no invn/soniclib/soniclib.h: point it at a checkout of github.com/tdk-invn-oss/ultrasonic.soniclib)
endif
$(info rp2040: the CH101 sensor layer over SonicLib in $(SONICLIB_DIR))
ifeq ($(origin BUILD),file)
BUILD := build/rp2040-soniclib
endif
RP_SONICLIB := 1
else
$(info rp2040: no SONICLIB_DIR: no sensor layer, the firmware streams its embedded recordings)
RP_SONICLIB := 0
endif
SDK := $(RP_DIR)/vendor/pico-sdk/src
TUSB := $(RP_DIR)/vendor/tinyusb/src
ARM_CC ?= arm-none-eabi-gcc
ARM_SIZE ?= arm-none-eabi-size
ARM_OBJCOPY ?= arm-none-eabi-objcopy
PYTHON ?= python3
SUBSET ?= ../../spiel_edge/data/spiel_icra23_subset.npz
RP_ARCH := -mcpu=cortex-m0plus -mthumb
RP_FW := -DSPIEL_FW_UPDATE=1 -DSPIEL_FW_EXEC_COPY=1 -DSPIEL_FW_TARGET=\"rp2040\" \
	-DRP2040_SONICLIB=$(RP_SONICLIB)
# samples a channel's buffer holds: I/Q (SonicLib) takes two values a sample, 4 x 64 I/Q
ifeq ($(RP_SONICLIB),1)
RP_FW += -DSPIEL_IQ_SAMPLES=1
RP_MAX_SAMPLES := 128
else
RP_MAX_SAMPLES := 64
endif
RP_VERSION ?= 1.0.0+rp2040
FW_SIGN_KEY ?= $(FW_KEY:.pub=.key)
RP_SECURITY_COUNTER ?= 0
RP_DEFS := -DPICO_RP2040=1 -DPICO_ON_DEVICE=1 -DPICO_NO_HARDWARE=0 -DPICO_BUILD=1 \
	-DPICO_32BIT=1 -DPICO_NO_FLASH=0 -DPICO_COPY_TO_RAM=0 -DPICO_USE_BLOCKED_RAM=0 \
	-DPICO_CXX_ENABLE_EXCEPTIONS=0 -DNDEBUG -DCFG_TUSB_MCU=OPT_MCU_RP2040 \
	-DLIB_PICO_PLATFORM=1 -DPICO_BOARD=\"pico\"
SDK_INCDIRS := rp2_common/pico_flash common/pico_base_headers rp2040/hardware_regs rp2040/hardware_structs \
	rp2040/pico_platform rp2_common/hardware_base rp2_common/hardware_sync \
	rp2_common/hardware_sync_spin_lock rp2_common/hardware_irq rp2_common/hardware_resets \
	rp2_common/hardware_timer rp2_common/hardware_clocks rp2_common/hardware_pll \
	rp2_common/hardware_xosc rp2_common/hardware_watchdog rp2_common/hardware_ticks \
	rp2_common/hardware_flash rp2_common/hardware_gpio rp2_common/pico_platform_compiler \
	rp2_common/pico_platform_sections rp2_common/pico_platform_panic rp2_common/pico_platform_common \
	rp2_common/boot_bootrom_headers rp2_common/pico_bootrom rp2_common/hardware_boot_lock \
	rp2_common/hardware_xip_cache common/boot_picoboot_headers common/boot_picobin_headers \
	boards
# vendor headers as system headers: their warnings are not ours
RP_SYSINC := -I$(RP_DIR)/sdk_config $(addprefix -isystem $(SDK)/,$(addsuffix /include,$(SDK_INCDIRS))) \
	-isystem $(TUSB)
RP_INC := $(INC) -I$(RP_DIR) -I$(BUILD) $(RP_SYSINC)
# the core: C99 and every warning, as on every target
RP_CORE_CFLAGS := $(RP_ARCH) $(WARN) -Os -g -ffunction-sections -fdata-sections -ffreestanding \
	-fstack-usage -DSPIEL_MAX_SAMPLES=$(RP_MAX_SAMPLES) $(RP_FW) $(CFLAGS_EXTRA)
# the port's own files: gnu11 (the SDK headers use static_assert and GNU extensions)
RP_PORT_CFLAGS := $(RP_ARCH) -MD $(filter-out -std=c99 -pedantic,$(WARN)) -std=gnu11 -Os -g \
	-ffunction-sections -fdata-sections -fstack-usage -DSPIEL_MAX_SAMPLES=$(RP_MAX_SAMPLES) $(RP_FW) $(RP_DEFS) \
	$(CFLAGS_EXTRA)
# the vendored SDK and TinyUSB files: as upstream builds them, warnings shown, not errors
RP_VENDOR_CFLAGS := $(RP_ARCH) -MD -std=gnu11 -Os -g -ffunction-sections -fdata-sections \
	-fstack-usage -Wall -Wno-unused-parameter $(RP_DEFS)
RP_LDFLAGS := $(RP_ARCH) -nostartfiles --specs=nano.specs -Wl,--gc-sections -L$(RP_DIR)

RP_PORT := main hal_rp2040 usb_rp2040 startup_rp2040 image_rp2040 boot_rp2040 clocks_rp2040
RP_CORE := $(basename $(notdir $(CORE_SRC)))
RP_SDK_SRC := rp2_common/hardware_clocks/clocks.c rp2_common/hardware_pll/pll.c \
	rp2_common/hardware_xosc/xosc.c rp2_common/hardware_watchdog/watchdog.c \
	rp2_common/hardware_ticks/ticks.c rp2_common/hardware_flash/flash.c \
	rp2_common/pico_bootrom/bootrom.c rp2040/pico_platform/platform.c
RP_TUSB_SRC := tusb.c common/tusb_fifo.c device/usbd.c device/usbd_control.c \
	class/cdc/cdc_device.c portable/raspberrypi/rp2040/dcd_rp2040.c \
	portable/raspberrypi/rp2040/rp2040_usb.c
RP_VENDOR := $(basename $(notdir $(RP_SDK_SRC) $(RP_TUSB_SRC)))
O := $(BUILD)/obj
RP_APP_OBJS := $(addprefix $(O)/,$(addsuffix .o,main hal_rp2040 usb_rp2040 startup_rp2040 \
	image_rp2040 clocks_rp2040 $(RP_CORE) $(RP_VENDOR) ascans))
RP_BOOT_OBJS := $(addprefix $(O)/,$(addsuffix .o,boot_rp2040 image_rp2040 clocks_rp2040 boot sha256 \
	verify monocypher monocypher-ed25519 spiel_proto flash bootrom clocks pll xosc ticks watchdog platform boot2))
RP_HDRS := $(wildcard include/*.h core/*.h $(PROTO)/*.h $(RP_DIR)/*.h $(VENDOR)/*.h) $(BUILD)/ascans.h \
	$(FW_KEY)
vpath %.c $(RP_DIR) core $(PROTO) $(VENDOR) $(BUILD) $(addprefix $(SDK)/,$(dir $(RP_SDK_SRC))) \
	$(addprefix $(TUSB)/,$(dir $(RP_TUSB_SRC)))

all:
ifeq ($(RP_SONICLIB),1)
# The sensor layer: our files with the port's flags (every warning an error), SonicLib's own
# files as upstream builds them (C99, warnings shown, not errors), its headers as system headers.
SL := $(SONICLIB_DIR)/invn/soniclib
SL_SRC := $(addprefix $(SL)/,ch_api.c ch_common.c ch_driver.c ch_math_utils.c ch_rangefinder.c \
	chbsp_dummy.c sensor_fw/ch101/ch101_gpr.c sensor_fw/ch101/ch101_gpr_fw.c)
SL_DEFS := -DINCLUDE_WHITNEY_SUPPORT -DCH_LOG_MODULE_LEVEL=6
SL_INC := -I$(RP_DIR)/sensor -isystem $(SONICLIB_DIR)
SL_OBJS := $(addprefix $(O)/sl_,$(addsuffix .o,$(basename $(notdir $(SL_SRC)))))
RP_SENSOR_OBJS := $(O)/iq_plan.o $(O)/chbsp_rp2040.o $(O)/sensor_soniclib.o
RP_APP_OBJS += $(RP_SENSOR_OBJS) $(SL_OBJS)
RP_SENSOR_HDRS := $(wildcard $(RP_DIR)/sensor/*.h)
$(O)/iq_plan.o: $(RP_DIR)/sensor/iq_plan.c $(RP_SENSOR_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_CORE_CFLAGS) -I$(RP_DIR)/sensor -c $< -o $@
$(O)/chbsp_rp2040.o $(O)/sensor_soniclib.o: $(O)/%.o: $(RP_DIR)/sensor/%.c $(RP_HDRS) $(RP_SENSOR_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_PORT_CFLAGS) $(SL_DEFS) $(RP_INC) $(SL_INC) -c $< -o $@
$(SL_OBJS): $(O)/sl_%.o: $(RP_DIR)/sensor/chirp_board_config.h
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_ARCH) -MD -std=gnu99 -Os -g -ffunction-sections -fdata-sections -fstack-usage \
		-Wall $(SL_DEFS) $(SL_INC) -c $(filter %/$*.c,$(SL_SRC)) -o $@
all: $(BUILD)/firmware.uf2
else
all: $(BUILD)/firmware.uf2 $(BUILD)/firmware-emu.uf2
endif
.PRECIOUS: $(BUILD)/%.bin $(BUILD)/%.elf $(BUILD)/%.img

$(BUILD)/ascans.c: targets/mps2-an386/gen_ascans.py $(SUBSET)
	@mkdir -p $(@D)
	$(PYTHON) targets/mps2-an386/gen_ascans.py $(SUBSET) $@
$(BUILD)/ascans.h: $(BUILD)/ascans.c

$(addprefix $(BUILD)/obj/,$(addsuffix .o,$(RP_CORE) ascans)): $(BUILD)/obj/%.o: %.c $(RP_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_CORE_CFLAGS) $(INC) -I$(BUILD) -c $< -o $@
$(addprefix $(BUILD)/obj/,$(addsuffix .o,$(RP_PORT) flash_rp2040)): $(BUILD)/obj/%.o: %.c $(RP_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_PORT_CFLAGS) $(RP_INC) -c $< -o $@
$(BUILD)/obj/flash_rp2040_emu.o: $(RP_DIR)/flash_rp2040.c $(RP_HDRS)
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_PORT_CFLAGS) -DRP2040_EMU_FLASH=1 $(RP_INC) -c $< -o $@
$(addprefix $(BUILD)/obj/,$(addsuffix .o,$(RP_VENDOR))): $(BUILD)/obj/%.o: %.c $(RP_DIR)/tusb_config.h
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_VENDOR_CFLAGS) -I$(RP_DIR) $(RP_SYSINC) -c $< -o $@

# boot2: assembled and linked alone, padded to 252 bytes, its CRC-32 appended (the bootrom
# checks it before it runs boot2), then assembled again as the .boot2 section
BOOT2_DIR := $(SDK)/rp2040/boot_stage2
$(BUILD)/boot2.elf: $(BOOT2_DIR)/boot2_w25q080.S
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_ARCH) -MD $(RP_DEFS) -I$(RP_DIR) $(RP_SYSINC) -I$(BOOT2_DIR)/asminclude \
		-nostdlib -Wl,--script=$(BOOT2_DIR)/boot_stage2.ld $< -o $@
$(BUILD)/boot2.S: $(BUILD)/boot2.elf
	$(ARM_OBJCOPY) -O binary $< $(BUILD)/boot2.bin
	$(PYTHON) $(BOOT2_DIR)/pad_checksum -s 0xffffffff $(BUILD)/boot2.bin $@
$(BUILD)/obj/boot2.o: $(BUILD)/boot2.S
	@mkdir -p $(@D)
	$(ARM_CC) $(RP_ARCH) -c $< -o $@

$(BUILD)/app.elf: $(RP_APP_OBJS) $(O)/flash_rp2040.o $(RP_DIR)/rp2040-app.ld $(RP_DIR)/rp2040-sections.ld
	$(ARM_CC) $(RP_LDFLAGS) -Trp2040-app.ld -Wl,-Map=$(BUILD)/app.map $(RP_APP_OBJS) $(O)/flash_rp2040.o -o $@
$(BUILD)/app-emu.elf: $(RP_APP_OBJS) $(O)/flash_rp2040_emu.o $(RP_DIR)/rp2040-app.ld $(RP_DIR)/rp2040-sections.ld
	$(ARM_CC) $(RP_LDFLAGS) -Trp2040-app.ld $(RP_APP_OBJS) $(O)/flash_rp2040_emu.o -o $@
$(BUILD)/boot.elf: $(RP_BOOT_OBJS) $(O)/flash_rp2040.o $(RP_DIR)/rp2040-boot.ld $(RP_DIR)/rp2040-sections.ld
	$(ARM_CC) $(RP_LDFLAGS) -Trp2040-boot.ld -Wl,-Map=$(BUILD)/boot.map $(RP_BOOT_OBJS) $(O)/flash_rp2040.o -o $@
$(BUILD)/boot-emu.elf: $(RP_BOOT_OBJS) $(O)/flash_rp2040_emu.o $(RP_DIR)/rp2040-boot.ld $(RP_DIR)/rp2040-sections.ld
	$(ARM_CC) $(RP_LDFLAGS) -Trp2040-boot.ld $(RP_BOOT_OBJS) $(O)/flash_rp2040_emu.o -o $@
$(BUILD)/%.bin: $(BUILD)/%.elf
	$(ARM_OBJCOPY) -O binary $< $@
$(BUILD)/%.img: $(BUILD)/%.bin $(RP_DIR)/pack_image.py $(FW_KEY)
	@test -f $(FW_SIGN_KEY) || { echo "rp2040: no $(FW_SIGN_KEY) to sign firmware.uf2's image with: set FW_SIGN_KEY=<the private half of $(FW_KEY)>" >&2; exit 1; }
	$(PYTHON) $(RP_DIR)/pack_image.py $< $(RP_VERSION) rp2040 $@ $(FW_SIGN_KEY) $(FW_KEY) $(RP_SECURITY_COUNTER)
	head -c 96 $@ > $(@:.img=.hdr)
# the boot stage at the flash's start, the image in slot 0 and installed in the execution region
$(BUILD)/firmware%uf2: $(BUILD)/boot%bin $(BUILD)/app%img $(RP_DIR)/uf2.py
	$(PYTHON) $(RP_DIR)/uf2.py $@ $(BUILD)/boot$*bin@0x10000000 $(BUILD)/app$*img@0x10090000 \
		$(BUILD)/app$*hdr@0x10010000 $(BUILD)/app$*bin@0x10011000
	$(ARM_SIZE) $(BUILD)/boot$*elf $(BUILD)/app$*elf

# the deepest stack chains (-fstack-usage frames along the direct calls of the ELF)
stack: $(BUILD)/firmware.uf2
	@$(PYTHON) $(RP_DIR)/stack_chain.py $(BUILD)/app.elf $(BUILD)/obj
	@$(PYTHON) $(RP_DIR)/stack_chain.py $(BUILD)/boot.elf $(BUILD)/obj boot_reset

.PHONY: stack
