# target.mk - Cortex-M4 cross builds of libfbgforce and the on-target golden-vector test
# (docs/firmware.md). Included from runtime_c/Makefile (`-include target.mk`) and from
# examples/firmware/Makefile; also usable alone: make -C runtime_c -f target.mk <target>
#
# Targets (everything goes to build/cm4*/, the host build is never touched):
#   target-lib            build/cm4/libfbgforce.a: fixed-point library, portable C,
#                         -mcpu=cortex-m4 -mthumb -mfloat-abi=soft
#   target-lib-dsp        build/cm4-dsp/libfbgforce.a: the same with FBG_USE_DSP=1 (src/fbg_dsp*.c:
#                         SMLALD/SMLAL/USAT inner loops of the MLP layers and the FIR)
#   target-lib-float      build/cm4f/libfbgforce_float.a: the float pipeline, hard float
#                         -mfpu=fpv4-sp-d16 -mfloat-abi=hard
#   target-check-nofloat  fails if either fixed-point cross library references a floating-point
#                         helper (__aeabi_f*, __aeabi_d*, int<->float conversions, libgcc's
#                         soft-float names): on soft-float ARM every float operation is such a call
#   target-libs           all three libraries + target-check-nofloat
#   target-test           golden vectors on QEMU for the portable and the DSP build, exit status =
#                         bit-exactness; prints the target report JSON. MODEL=<model dir> picks the
#                         model (default: a model trained on the `smoke` scene by the report tool)
#
# Tools: apt-get install --no-install-recommends gcc-arm-none-eabi libnewlib-arm-none-eabi
#        qemu-system-arm

TARGET_DIR        := $(dir $(lastword $(MAKEFILE_LIST)))
TARGET_CROSS      ?= arm-none-eabi-
TARGET_CC         := $(TARGET_CROSS)gcc
TARGET_AR         := $(TARGET_CROSS)ar
TARGET_NM         := $(TARGET_CROSS)nm
TARGET_BUILD      := build/cm4
TARGET_BUILD_DSP  := build/cm4-dsp
TARGET_BUILD_FLOAT := build/cm4f
TARGET_PYTHON     ?= python3

# Same split as runtime_c/Makefile: src/fbg_*.c fixed point, src/fbgf_*.c the float build.
TARGET_FIXED_SRCS := $(sort $(wildcard $(TARGET_DIR)src/fbg_*.c))
TARGET_FLOAT_SRCS := $(sort $(wildcard $(TARGET_DIR)src/fbgf_*.c))
TARGET_ALL_SRCS   := $(TARGET_FIXED_SRCS) $(TARGET_FLOAT_SRCS)
TARGET_HDRS       := $(wildcard $(TARGET_DIR)include/*.h $(TARGET_DIR)src/*.h)

TARGET_WARN       := -std=c99 -Wall -Wextra -Werror -pedantic
# -ffunction/-fdata-sections so that a firmware link with --gc-sections keeps only what it calls.
TARGET_CFLAGS     := $(TARGET_WARN) -O2 -mcpu=cortex-m4 -mthumb -ffunction-sections -fdata-sections \
                     -fstack-usage
TARGET_SOFT       := -mfloat-abi=soft
TARGET_HARD       := -mfpu=fpv4-sp-d16 -mfloat-abi=hard
TARGET_INC        := -I$(TARGET_DIR)include -I$(TARGET_DIR)src

# Undefined symbols that mean "floating point happened" in a soft-float ARM object.
TARGET_FLOAT_SYMS := __aeabi_[fd]|__aeabi_u?[il]2[fd]|__(add|sub|mul|div|neg|cmp|eq|ne|lt|le|gt|ge|unord)[sdt]f[23]|__float|__fix|__extend|__trunc|^(sqrt|exp|log|pow|sin|cos|tan|fabs|floor|ceil|round)f?$$

TARGET_LIB        := $(TARGET_DIR)$(TARGET_BUILD)/libfbgforce.a
TARGET_LIB_DSP    := $(TARGET_DIR)$(TARGET_BUILD_DSP)/libfbgforce.a
TARGET_LIB_FLOAT  := $(TARGET_DIR)$(TARGET_BUILD_FLOAT)/libfbgforce_float.a

.PHONY: target-lib target-lib-dsp target-lib-float target-check-nofloat target-libs target-test

target-lib: $(TARGET_LIB)
target-lib-dsp: $(TARGET_LIB_DSP)
target-lib-float: $(TARGET_LIB_FLOAT)

$(TARGET_DIR)$(TARGET_BUILD)/obj/%.o: $(TARGET_DIR)src/%.c $(TARGET_HDRS)
	@mkdir -p $(@D)
	$(TARGET_CC) $(TARGET_CFLAGS) $(TARGET_SOFT) -DFBG_USE_DSP=0 $(TARGET_INC) -c -o $@ $<

$(TARGET_DIR)$(TARGET_BUILD_DSP)/obj/%.o: $(TARGET_DIR)src/%.c $(TARGET_HDRS)
	@mkdir -p $(@D)
	$(TARGET_CC) $(TARGET_CFLAGS) $(TARGET_SOFT) -DFBG_USE_DSP=1 $(TARGET_INC) -c -o $@ $<

# The float library also carries the fixed-point objects it shares (version, blob loader),
# compiled for the hard-float ABI so that one firmware can link it alone.
$(TARGET_DIR)$(TARGET_BUILD_FLOAT)/obj/%.o: $(TARGET_DIR)src/%.c $(TARGET_HDRS)
	@mkdir -p $(@D)
	$(TARGET_CC) $(TARGET_CFLAGS) $(TARGET_HARD) -DFBG_USE_DSP=0 $(TARGET_INC) -c -o $@ $<

target_objs = $(patsubst $(TARGET_DIR)src/%.c,$(TARGET_DIR)$(1)/obj/%.o,$(2))

$(TARGET_LIB): $(call target_objs,$(TARGET_BUILD),$(TARGET_FIXED_SRCS))
	@rm -f $@
	$(TARGET_AR) rcs $@ $^

$(TARGET_LIB_DSP): $(call target_objs,$(TARGET_BUILD_DSP),$(TARGET_FIXED_SRCS))
	@rm -f $@
	$(TARGET_AR) rcs $@ $^

$(TARGET_LIB_FLOAT): $(call target_objs,$(TARGET_BUILD_FLOAT),$(TARGET_ALL_SRCS))
	@rm -f $@
	$(TARGET_AR) rcs $@ $^

target-check-nofloat: $(TARGET_LIB) $(TARGET_LIB_DSP)
	@for lib in $^; do \
	    bad=$$($(TARGET_NM) -u $$lib | awk '{print $$NF}' | grep -E '$(TARGET_FLOAT_SYMS)' | sort -u); \
	    if [ -n "$$bad" ]; then echo "floating point in $$lib: $$bad" >&2; exit 1; fi; \
	    echo "$$lib: no floating-point helpers"; \
	done

target-libs: target-lib target-lib-dsp target-lib-float target-check-nofloat

# Runs from the repository root (one level above runtime_c/) so the package imports.
target-test: target-libs
	cd $(TARGET_DIR).. && $(TARGET_PYTHON) -m fbgforce.target $(if $(MODEL),--model $(abspath $(MODEL))) --json
