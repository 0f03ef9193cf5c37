#!/bin/sh
# Usage: count_window.sh fw.elf insn_window.so [out-file]
# Runs the golden replay under QEMU with the instruction-window plugin: one window per fbg_step
# (see insn_window_plugin.c); prints the plugin's summary. Exit status = the firmware's.
elf=$1; plugin=$2; out=${3:-/dev/stderr}
sym() { arm-none-eabi-nm -S "$elf" | awk -v s="$1" '$4==s{print $1, $2}'; }
lo() { set -- $(sym "$1"); echo $(( 0x$1 & ~1 )); }
hi() { set -- $(sym "$1"); echo $(( (0x$1 & ~1) + 0x$2 )); }
args="begin=$(lo fbg_mark_begin),end=$(lo fbg_mark_end)"
for f in fbg_mark_begin fbg_mark_end fw_timed_step; do args="$args,ex=$(lo $f):$(hi $f)"; done
qemu-system-arm -M mps2-an386 -nographic -semihosting -kernel "$elf" \
    -plugin "$plugin,$args,out=$out" </dev/null
