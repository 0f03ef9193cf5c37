# hardening.mk - sanitizer, valgrind and fuzz targets for the fbgforce runtime (docs/robustness.md).
#
# Included from runtime_c/Makefile (`-include hardening.mk`); also usable alone:
#     make -C runtime_c -f hardening.mk <target>
#
# Targets (all build into build/hardening/ and never touch the normal library build):
#   asan-driver     the hard-case driver built with AddressSanitizer + UndefinedBehaviorSanitizer
#                   (every UB report aborts: -fno-sanitize-recover=all)
#   asan-check      runs the whole hard-case suite (tests/test_hardcases*.py) through that driver
#   valgrind-check  the same suite with the plain -g driver under valgrind memcheck
#                   (any error or leak fails: --error-exitcode, --errors-for-leak-kinds=all)
#   fuzz            the two libFuzzer targets (clang): fuzz_step, fuzz_blob
#   fuzz-run        runs each fuzzer FUZZ_SECONDS (default 20) from the committed corpus in
#                   fuzz/corpus/<target>; new inputs go to build/, the corpus stays unchanged
#   fuzz-corpus     regenerates the committed fuzz models and seed corpus (fuzz/hardcases.py)
#   hardening-check asan-check + valgrind-check + fuzz-run

HARD_DIR      := $(dir $(lastword $(MAKEFILE_LIST)))
HARD_BUILD    ?= $(HARD_DIR)build/hardening
HARD_SRC      := $(sort $(wildcard $(HARD_DIR)src/*.c))
HARD_INC      := -I$(HARD_DIR)include
HARD_HDR      := $(wildcard $(HARD_DIR)include/*.h $(HARD_DIR)src/*.h)
PYTHON        ?= python3
FUZZ_SECONDS  ?= 20
HARD_CC       ?= gcc
FUZZ_CC       ?= clang
HARD_WARN     := -std=c99 -Wall -Wextra -Werror -pedantic
# The suite selection the sanitized / valgrind runs execute (pytest node ids or paths).
# (the valgrind and fuzz tests are left out: these targets ARE those runs, suite-wide).
HARDCASE_TESTS ?= tests/test_hardcases_inputs.py tests/test_hardcases_bounds.py -k "not valgrind_memcheck and not fuzzers_bounded"

SAN_FLAGS     := -g -O1 -fno-omit-frame-pointer -fsanitize=address,undefined \
                 -fno-sanitize-recover=all -fsanitize=float-divide-by-zero,float-cast-overflow
# Shifts of negative numbers and signed overflow are what fixed-point code gets wrong, so they
# are checked explicitly on top of -fsanitize=undefined's defaults.
SAN_FLAGS     += -fsanitize=shift,signed-integer-overflow,bounds

ASAN_DRIVER   := $(HARD_BUILD)/asan/hardcase_driver
PLAIN_DRIVER  := $(HARD_BUILD)/plain/hardcase_driver
FUZZERS       := $(HARD_BUILD)/fuzz/fuzz_step $(HARD_BUILD)/fuzz/fuzz_blob
DRIVER_SRC    := $(HARD_DIR)fuzz/hardcase_driver.c
FUZZ_COMMON   := $(HARD_DIR)fuzz/fuzz_common.h

# Sanitizer reports must fail the run, and leaks count (the library must not allocate at all).
HARD_ASAN_ENV := ASAN_OPTIONS=abort_on_error=1:detect_leaks=1:strict_string_checks=1:detect_stack_use_after_return=1 \
                 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
VALGRIND      ?= valgrind
VALGRIND_CMD  := $(VALGRIND) -q --tool=memcheck --error-exitcode=97 --leak-check=full \
                 --errors-for-leak-kinds=all --show-leak-kinds=all --track-origins=yes

.PHONY: asan-driver plain-driver asan-check valgrind-check fuzz fuzz-run fuzz-corpus hardening-check

asan-driver: $(ASAN_DRIVER)
plain-driver: $(PLAIN_DRIVER)

$(ASAN_DRIVER): $(DRIVER_SRC) $(HARD_SRC) $(HARD_HDR) $(FUZZ_COMMON)
	@mkdir -p $(@D)
	$(HARD_CC) $(HARD_WARN) $(SAN_FLAGS) $(HARD_INC) -o $@ $(DRIVER_SRC) $(HARD_SRC)

$(PLAIN_DRIVER): $(DRIVER_SRC) $(HARD_SRC) $(HARD_HDR) $(FUZZ_COMMON)
	@mkdir -p $(@D)
	$(HARD_CC) $(HARD_WARN) -g -O1 $(HARD_INC) -o $@ $(DRIVER_SRC) $(HARD_SRC)

# The pytest suite runs every hard case through the cffi module and the integer reference;
# FBGFORCE_HARDCASE_DRIVER makes it also run each case through this external driver and demand
# the same bits. The repository root is one level above runtime_c/.
asan-check: $(ASAN_DRIVER)
	cd $(HARD_DIR).. && $(HARD_ASAN_ENV) FBGFORCE_HARDCASE_DRIVER=$(abspath $(ASAN_DRIVER)) \
	    $(PYTHON) -m pytest -q -p no:cacheprovider $(HARDCASE_TESTS)

valgrind-check: $(PLAIN_DRIVER)
	cd $(HARD_DIR).. && FBGFORCE_HARDCASE_DRIVER=$(abspath $(PLAIN_DRIVER)) \
	    FBGFORCE_HARDCASE_WRAPPER="$(VALGRIND_CMD)" \
	    $(PYTHON) -m pytest -q -p no:cacheprovider $(HARDCASE_TESTS)

# libFuzzer needs clang. The library sources get the same sanitizers as the harness.
FUZZ_FLAGS := -g -O1 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
              -fsanitize=shift,signed-integer-overflow,bounds

fuzz: $(FUZZERS)

$(HARD_BUILD)/fuzz/fuzz_%: $(HARD_DIR)fuzz/fuzz_%.c $(HARD_SRC) $(HARD_HDR) $(FUZZ_COMMON)
	@mkdir -p $(@D)
	$(FUZZ_CC) -std=c99 -Wall -Wextra -Werror $(FUZZ_FLAGS) $(HARD_INC) \
	    -DFBG_FUZZ_MODELS_DIR='"$(abspath $(HARD_DIR)fuzz/models)"' -o $@ $< $(HARD_SRC)

# Each fuzzer reads the committed corpus (second directory: read only) and writes what it finds
# to build/ (first directory), so a CI run never dirties the work tree. A crash leaves
# crash-* in build/hardening/fuzz/ and fails the target.
fuzz-run: $(FUZZERS)
	@for f in $(notdir $(FUZZERS)); do \
	    mkdir -p $(HARD_BUILD)/fuzz/new-$$f || exit 1; \
	    echo "== $$f for $(FUZZ_SECONDS) s"; \
	    $(HARD_ASAN_ENV) $(HARD_BUILD)/fuzz/$$f -max_total_time=$(FUZZ_SECONDS) -timeout=5 \
	        -rss_limit_mb=1024 -print_final_stats=1 \
	        -artifact_prefix=$(HARD_BUILD)/fuzz/$$f- \
	        $(HARD_BUILD)/fuzz/new-$$f $(HARD_DIR)fuzz/corpus/$$f >$(HARD_BUILD)/fuzz/$$f.log 2>&1; \
	    rc=$$?; tail -n 14 $(HARD_BUILD)/fuzz/$$f.log; \
	    if [ $$rc -ne 0 ]; then echo "$$f FAILED (exit $$rc), see $(HARD_BUILD)/fuzz/$$f.log"; exit 1; fi; \
	done

fuzz-corpus:
	cd $(HARD_DIR).. && $(PYTHON) runtime_c/fuzz/hardcases.py

hardening-check: asan-check valgrind-check fuzz-run
