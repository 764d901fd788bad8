# targets/mps2-an386/target.mk - the Cortex-M4 images for qemu-system-arm -M mps2-an386,
# included by ../../Makefile for TARGET=mps2 and TARGET=mps2-bringup (frame echo over the UART,
# no core, linked at 0 and booted directly). Output: $(BUILD)/firmware.elf, what qemu's -kernel
# loads, and firmware.map.
# TARGET=mps2 builds three things (docs/firmware.md, "Firmware update with rollback"):
#   app.elf, app.bin  the firmware (core + frame layer + this HAL), linked for EXEC_BASE; app.bin
#                     is the body `spiel-edge firmware pack --target mps2-an386` wraps
#   boot.elf          the boot stage alone (boot_mps2.c, the core's boot.c, sha256.c, verify.c
#                     and the vendored Ed25519 verifier)
#   firmware.elf      the boot stage at 0 plus app.bin at EXEC_BASE as the built-in image
# `make TARGET=mps2 sizes`: flash and RAM of the core and the frame layer (docs/firmware.md),
# the sample and staging buffers named apart, and the boot stage.
MPS2_DIR := targets/mps2-an386
ARM_CC ?= arm-none-eabi-gcc
ARM_SIZE ?= arm-none-eabi-size
ARM_OBJCOPY ?= arm-none-eabi-objcopy
PYTHON ?= python3
SUBSET ?= ../../spiel_edge/data/spiel_icra23_subset.npz
MPS2_ARCH := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
# the embedded A-scans have 64 samples: the core's sample buffer needs no more
MPS2_DEFINES ?= -DSPIEL_MAX_SAMPLES=64
ifeq ($(TARGET),mps2)
MPS2_FW := -DSPIEL_FW_UPDATE=1 -DSPIEL_FW_FACTORY=1 -DSPIEL_FW_EXEC_COPY=1 -DSPIEL_FW_TARGET=\"mps2-an386\"
endif
MPS2_CFLAGS := $(MPS2_ARCH) $(WARN) -Wstack-usage=1024 -Os -g -ffunction-sections -fdata-sections -ffreestanding \
	$(INC) -I$(MPS2_DIR) -I$(BUILD) $(MPS2_DEFINES) $(MPS2_FW) $(CFLAGS_EXTRA)
MPS2_LDFLAGS := $(MPS2_ARCH) -nostartfiles --specs=nano.specs -L$(MPS2_DIR) -Wl,--gc-sections
MPS2_SRCS := $(MPS2_DIR)/startup.c $(MPS2_DIR)/hal_mps2.c $(MPS2_DIR)/nor_mps2.c \
	$(MPS2_DIR)/syscalls.c $(BUILD)/ascans.c
BOOT_SRCS := $(MPS2_DIR)/boot_mps2.c $(MPS2_DIR)/image_mps2.c $(MPS2_DIR)/nor_mps2.c \
	core/boot.c core/sha256.c core/verify.c $(PROTO)/spiel_proto.c $(VENDOR_SRC)
ifeq ($(TARGET),mps2-bringup)
MPS2_SRCS += $(MPS2_DIR)/bringup.c $(PROTO)/spiel_proto.c
else
MPS2_SRCS += $(MPS2_DIR)/main.c $(MPS2_DIR)/image_mps2.c $(CORE_SRC)
endif
MPS2_OBJS := $(patsubst %.c,$(BUILD)/obj/%.o,$(notdir $(MPS2_SRCS)))
BOOT_OBJS := $(patsubst %.c,$(BUILD)/obj/%.o,$(notdir $(BOOT_SRCS)))
vpath %.c $(MPS2_DIR) core $(PROTO) $(VENDOR) $(BUILD)

all: $(BUILD)/firmware.elf

$(BUILD)/ascans.c: $(MPS2_DIR)/gen_ascans.py $(SUBSET)
	@mkdir -p $(@D)
	$(PYTHON) $(MPS2_DIR)/gen_ascans.py $(SUBSET) $@

$(BUILD)/ascans.h: $(BUILD)/ascans.c

$(BUILD)/obj/%.o: %.c $(BUILD)/ascans.h $(FW_KEY) $(wildcard include/*.h core/*.h $(PROTO)/*.h $(MPS2_DIR)/*.h $(VENDOR)/*.h)
	@mkdir -p $(@D)
	$(ARM_CC) $(MPS2_CFLAGS) -c $< -o $@

ifeq ($(TARGET),mps2-bringup)
$(BUILD)/firmware.elf: $(MPS2_OBJS) $(MPS2_DIR)/mps2-an386.ld $(MPS2_DIR)/mps2-sections.ld
	$(ARM_CC) $(MPS2_LDFLAGS) -Tmps2-an386.ld -Wl,-Map=$(BUILD)/firmware.map $(MPS2_OBJS) -o $@
	$(ARM_SIZE) $@
else
$(BUILD)/app.elf: $(MPS2_OBJS) $(MPS2_DIR)/mps2-app.ld $(MPS2_DIR)/mps2-sections.ld
	$(ARM_CC) $(MPS2_LDFLAGS) -Tmps2-app.ld -Wl,-Map=$(BUILD)/app.map $(MPS2_OBJS) -o $@

$(BUILD)/app.bin: $(BUILD)/app.elf
	$(ARM_OBJCOPY) -O binary $< $@

$(BUILD)/obj/factory.o: $(MPS2_DIR)/factory.S $(BUILD)/app.bin
	@mkdir -p $(@D)
	$(ARM_CC) $(MPS2_ARCH) -DFACTORY_BIN='"$(abspath $(BUILD)/app.bin)"' -c $< -o $@

$(BUILD)/boot.elf: $(BOOT_OBJS) $(MPS2_DIR)/mps2-boot.ld $(MPS2_DIR)/mps2-sections.ld
	$(ARM_CC) $(MPS2_LDFLAGS) -Tmps2-boot.ld -Wl,-Map=$(BUILD)/boot.map $(BOOT_OBJS) -o $@

$(BUILD)/firmware.elf: $(BUILD)/boot.elf $(BUILD)/obj/factory.o
	$(ARM_CC) $(MPS2_LDFLAGS) -Tmps2-boot.ld -Wl,-Map=$(BUILD)/firmware.map $(BOOT_OBJS) \
		$(BUILD)/obj/factory.o -o $@
	$(ARM_SIZE) $(BUILD)/app.elf $(BUILD)/boot.elf
endif

CORE_OBJS := $(filter $(BUILD)/obj/device.o $(BUILD)/obj/link.o $(BUILD)/obj/config_store.o $(BUILD)/obj/spiel_proto.o,$(MPS2_OBJS))
PROTOCOL2_OBJS := $(filter $(BUILD)/obj/telemetry.o $(BUILD)/obj/update.o $(BUILD)/obj/boot.o $(BUILD)/obj/sha256.o,$(MPS2_OBJS))
ARM_NM ?= arm-none-eabi-nm

sizes: $(BUILD)/firmware.elf
	@echo "core + frame layer, Cortex-M4 -Os ($(MPS2_DEFINES) $(MPS2_FW) $(CFLAGS_EXTRA)):"
	@$(ARM_SIZE) -t $(CORE_OBJS)
	@echo "protocol version 2 in the core (time sync, telemetry, firmware update):"
	@$(ARM_SIZE) -t $(PROTOCOL2_OBJS)
	@echo "signed images (core/verify.c and the vendored Ed25519 verifier, vendor/monocypher):"
	@$(ARM_SIZE) -t $(filter $(BUILD)/obj/verify.o $(BUILD)/obj/monocypher.o $(BUILD)/obj/monocypher-ed25519.o,$(MPS2_OBJS))
	@echo "their largest RAM buffers (bytes):"
	@$(ARM_NM) -S --size-sort -t d $(CORE_OBJS) $(PROTOCOL2_OBJS) | awk '$$3 ~ /^[bBdD]$$/ && $$2 + 0 >= 64 {print "  " $$4, $$2 + 0}'
	@echo "library routines linked into the application (bytes; entry points that share code, once):"
	@$(ARM_NM) -S -t d $(BUILD)/app.elf | awk '$$3 ~ /^[tT]$$/ && $$4 ~ /^(__|mem|str)/' | sort -n | \
		awk '{s = $$1 + 0; e = s + $$2; if (s >= end) n += e - s; else if (e > end) n += e - end; if (e > end) end = e; print "  " $$4, $$2 + 0} END {print "  total", n}'
	@echo "the boot stage (boot.elf: text = its flash, bss + stack = its RAM) and the application:"
	@$(ARM_SIZE) $(BUILD)/boot.elf $(BUILD)/app.elf

.PHONY: sizes

# The Ed25519 check (vendor/monocypher) takes 1.2 KiB of stack in one frame (its point tables):
# the boot stage has 4 KiB, the application 8 KiB; its files get a bound of their own.
$(BUILD)/obj/monocypher.o $(BUILD)/obj/monocypher-ed25519.o: MPS2_CFLAGS += -Wstack-usage=1536
