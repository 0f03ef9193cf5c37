"""``fbgforce target-report``: the runtime on a real instruction set (Cortex-M4 under QEMU).

One call cross-compiles ``libfbgforce`` twice (portable C and the DSP-extension build,
``runtime_c/target.mk``), generates the model's C source and a file of golden vectors from the
numpy integer reference (:mod:`fbgforce.export.intref`), links the bare-metal replay program of
``examples/firmware/``, runs it on QEMU ``mps2-an386`` and reports:

- ``bit_exact``: every output bit of every golden record equal, in BOTH builds (the firmware
  compares the whole ``fbg_output`` struct and every return status; its exit status says so);
- exact executed-instruction counts per ``fbg_step`` from the TCG plugin
  ``examples/firmware/insn_window_plugin.c`` (one window per call, harness excluded);
- MACs per step (FIR ``4 * n_taps`` + every layer ``n_in * n_out`` of the nets that ran);
- flash and RAM from a minimal firmware (``main_size.c``): every linked section that does not
  come from the harness, i.e. library + model + the libc/libgcc helpers they pull in;
- the fraction of a 1 kHz period the worst step takes on a 168 MHz core, ASSUMING ONE
  INSTRUCTION PER CYCLE (QEMU has no timing model; on a real M4 loads not pipelined with a
  neighbouring load take 2 cycles and taken branches 2-4, so real cycles are somewhat higher).

The golden session (:func:`fbgforce.target.golden.golden_session`) drives the whole API, not
only ``fbg_step``: steps before any tare, a tare through ``fbg_tare_begin/add/end`` (with
rejected samples), a recording replayed on that tare, ``fbg_set_baseline`` with edge-case
samples (lost peaks, jumps, sentinels, values that saturate), error returns, ``fbg_reset`` and
a fresh ``fbg_init``.

Tools: ``apt-get install --no-install-recommends gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm`` (plus ``make`` and a host ``gcc`` for the plugin).

The C sources come with the package: a regular install ships the header, the library sources,
``target.mk`` and the firmware (with the plugin) as package data, an editable install uses the
repository's (:mod:`fbgforce.target.sources`); every build runs in a staged copy.

Modules: :mod:`~fbgforce.target.toolchain` (tools and the apt line),
:mod:`~fbgforce.target.sources` (the C tree), :mod:`~fbgforce.target.golden` (golden vectors),
:mod:`~fbgforce.target.firmware` (build, run under QEMU, count, sizes),
:mod:`~fbgforce.target.report` (the figures), :mod:`~fbgforce.target.cli` (the command).
"""
