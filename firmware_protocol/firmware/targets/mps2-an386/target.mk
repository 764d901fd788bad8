# targets/mps2-an386/target.mk - the Cortex-M4 image for qemu-system-arm -M mps2-an386,
# included by ../../Makefile for TARGET=mps2 (the firmware: core + frame layer + this HAL)
# and TARGET=mps2-bringup (frame echo over the UART, no core). Output: $(BUILD)/firmware.elf
# and firmware.map. `make TARGET=mps2 sizes`: flash and RAM of the core and the frame layer
# (docs/firmware.md), the sample and staging buffers named apart.
MPS2_DIR := targets/mps2-an386
ARM_CC ?= arm-none-eabi-gcc
ARM_SIZE ?= arm-none-eabi-size
PYTHON ?= python3
SUBSET ?= ../../spiel_edge/data/spiel_icra23_subset.npz
MPS2_ARCH := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
# the embedded A-scans have 64 samples: the core's sample buffer needs no more
MPS2_DEFINES ?= -DSPIEL_MAX_SAMPLES=64
MPS2_CFLAGS := $(MPS2_ARCH) $(WARN) -Os -g -ffunction-sections -fdata-sections -ffreestanding \
	$(INC) -I$(MPS2_DIR) -I$(BUILD) $(MPS2_DEFINES) $(CFLAGS_EXTRA)
MPS2_LDFLAGS := $(MPS2_ARCH) -nostartfiles --specs=nano.specs -T$(MPS2_DIR)/mps2-an386.ld \
	-Wl,--gc-sections -Wl,-Map=$(BUILD)/firmware.map
MPS2_SRCS := $(MPS2_DIR)/startup.c $(MPS2_DIR)/hal_mps2.c $(MPS2_DIR)/syscalls.c \
	$(BUILD)/ascans.c
ifeq ($(TARGET),mps2-bringup)
MPS2_SRCS += $(MPS2_DIR)/bringup.c $(PROTO)/spiel_proto.c
else
MPS2_SRCS += $(MPS2_DIR)/main.c $(CORE_SRC)
endif
MPS2_OBJS := $(patsubst %.c,$(BUILD)/obj/%.o,$(notdir $(MPS2_SRCS)))
vpath %.c $(MPS2_DIR) core $(PROTO) $(BUILD)

all: $(BUILD)/firmware.elf

$(BUILD)/ascans.c: $(MPS2_DIR)/gen_ascans.py $(SUBSET)
	@mkdir -p $(@D)
	$(PYTHON) $(MPS2_DIR)/gen_ascans.py $(SUBSET) $@

$(BUILD)/ascans.h: $(BUILD)/ascans.c

$(BUILD)/obj/%.o: %.c $(BUILD)/ascans.h $(wildcard include/*.h core/*.h $(PROTO)/*.h $(MPS2_DIR)/*.h)
	@mkdir -p $(@D)
	$(ARM_CC) $(MPS2_CFLAGS) -c $< -o $@

$(BUILD)/firmware.elf: $(MPS2_OBJS) $(MPS2_DIR)/mps2-an386.ld
	$(ARM_CC) $(MPS2_LDFLAGS) $(MPS2_OBJS) -o $@
	$(ARM_SIZE) $@

CORE_OBJS := $(filter $(BUILD)/obj/device.o $(BUILD)/obj/config_store.o $(BUILD)/obj/spiel_proto.o,$(MPS2_OBJS))
ARM_NM ?= arm-none-eabi-nm

sizes: $(BUILD)/firmware.elf
	@echo "core + frame layer, Cortex-M4 -Os ($(MPS2_DEFINES) $(CFLAGS_EXTRA)):"
	@$(ARM_SIZE) -t $(CORE_OBJS)
	@echo "their largest RAM buffers (bytes):"
	@$(ARM_NM) -S --size-sort -t d $(CORE_OBJS) | awk '$$3 ~ /^[bBdD]$$/ && $$2 + 0 >= 64 {print "  " $$4, $$2 + 0}'
	@echo "library routines linked into the whole image (bytes, aliases once):"
	@$(ARM_NM) -S -t d $(BUILD)/firmware.elf | awk '$$3 ~ /^[tT]$$/ && $$4 ~ /^(__|mem|str)/ && !seen[$$1]++ {n += $$2; print "  " $$4, $$2 + 0} END {print "  total", n}'

.PHONY: sizes
