# fuzz/fuzz.mk - the libFuzzer harness of the device's request decoder (fuzz_request.c),
# included by ../Makefile for TARGET=fuzz, with firmware update and I/Q (the harness implements
# the image slots and hal_acq_read_iq). Needs clang with its fuzzer runtime (Debian:
# clang and libclang-rt-<version>-dev). Output: $(BUILD)/spiel_fuzz. Run it with
# `python -m tools.release.firmware_fuzz`.
FUZZ_CC ?= clang
# FUZZ_COVERAGE=-fno-sanitize-coverage=trace-cmp: about 3x the inputs per second, without
# libFuzzer's comparison-guided mutations (for long runs over a corpus grown with them)
FUZZ_COVERAGE ?=
# -Icore: the harness is the core's white-box test (it checks a slot with the core's own
# SHA-256); targets never see core/ (spiel_boot.h is what a boot stage uses)
FUZZ_CFLAGS := $(WARN) -O1 -g -DSPIEL_FW_UPDATE=1 -DSPIEL_FW_EXEC_COPY=1 -DSPIEL_IQ_SAMPLES=1 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
	-fno-omit-frame-pointer $(FUZZ_COVERAGE) $(INC) -Icore $(CFLAGS_EXTRA)
FUZZ_OUT := $(BUILD)/spiel_fuzz

all: $(FUZZ_OUT)

$(FUZZ_OUT): fuzz/fuzz_request.c $(CORE_SRC) $(FW_KEY) $(wildcard include/*.h core/*.h $(PROTO)/*.h $(VENDOR)/*.h)
	@mkdir -p $(BUILD)
	$(FUZZ_CC) $(FUZZ_CFLAGS) fuzz/fuzz_request.c $(CORE_SRC) -o $@
