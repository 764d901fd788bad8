# targets/mps2-an386/target.mk - the Cortex-M4 image for qemu-system-arm -M mps2-an386,
# included by ../../Makefile for TARGET=mps2 (the firmware: core + frame layer + this HAL)
# and TARGET=mps2-bringup (frame echo over the UART, no core). Output: $(BUILD)/firmware.elf
# and firmware.map; `arm-none-eabi-size` of the image and of each object is printed.
MPS2_DIR := targets/mps2-an386
ARM_CC ?= arm-none-eabi-gcc
ARM_SIZE ?= arm-none-eabi-size
PYTHON ?= python3
SUBSET ?= ../../spiel_edge/data/spiel_icra23_subset.npz
MPS2_ARCH := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
MPS2_CFLAGS := $(MPS2_ARCH) $(WARN) -Os -g -ffunction-sections -fdata-sections -ffreestanding \
	$(INC) -I$(MPS2_DIR) -I$(BUILD) $(CFLAGS_EXTRA)
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
