# targets/mps2-an386/target.mk - the Cortex-M4 image for qemu-system-arm -M mps2-an386.
# Included by ../../Makefile for TARGET=mps2 (the firmware) and TARGET=mps2-bringup
# (frame echo without the core). Outputs under build/mps2/.
MPS2_DIR := targets/mps2-an386
MPS2_OUT := $(BUILD)/$(TARGET)
ARM_CC ?= arm-none-eabi-gcc
ARM_SIZE ?= arm-none-eabi-size
PYTHON ?= python3
SUBSET ?= ../../spiel_edge/data/spiel_icra23_subset.npz
MPS2_ARCH := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
MPS2_CFLAGS := $(MPS2_ARCH) -std=c99 -Os -g -Wall -Wextra -Werror -pedantic \
	-ffunction-sections -fdata-sections -ffreestanding \
	-Iinclude -I../c -I$(MPS2_DIR) -I$(MPS2_OUT)
MPS2_LDFLAGS := $(MPS2_ARCH) -nostartfiles --specs=nano.specs -T$(MPS2_DIR)/mps2-an386.ld \
	-Wl,--gc-sections -Wl,-Map=$(MPS2_OUT)/firmware.map
MPS2_SRCS := $(MPS2_DIR)/startup.c $(MPS2_DIR)/hal_mps2.c $(MPS2_DIR)/syscalls.c \
	../c/spiel_proto.c $(MPS2_OUT)/ascans.c
ifeq ($(TARGET),mps2-bringup)
MPS2_SRCS += $(MPS2_DIR)/bringup.c
else
MPS2_SRCS += $(MPS2_DIR)/main.c $(CORE_SRCS)
endif
MPS2_OBJS := $(patsubst %.c,$(MPS2_OUT)/obj/%.o,$(subst ../,up/,$(MPS2_SRCS)))

all: $(MPS2_OUT)/firmware.elf

$(MPS2_OUT)/ascans.c: $(MPS2_DIR)/gen_ascans.py $(SUBSET)
	@mkdir -p $(@D)
	$(PYTHON) $(MPS2_DIR)/gen_ascans.py $(SUBSET) $@

$(MPS2_OUT)/ascans.h: $(MPS2_OUT)/ascans.c

$(MPS2_OUT)/obj/up/%.o: ../%.c $(MPS2_OUT)/ascans.h
	@mkdir -p $(@D)
	$(ARM_CC) $(MPS2_CFLAGS) -c $< -o $@

$(MPS2_OUT)/obj/%.o: %.c $(MPS2_OUT)/ascans.h
	@mkdir -p $(@D)
	$(ARM_CC) $(MPS2_CFLAGS) -c $< -o $@

$(MPS2_OUT)/firmware.elf: $(MPS2_OBJS) $(MPS2_DIR)/mps2-an386.ld
	$(ARM_CC) $(MPS2_LDFLAGS) $(MPS2_OBJS) -o $@
	$(ARM_SIZE) $@
