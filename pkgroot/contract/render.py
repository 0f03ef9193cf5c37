"""The text the runtime contract (:mod:`fbgforce.contract`) derives: the marked sections of
``runtime_c/include/fbgforce.h``, ``runtime_c/src/fbg_contract.c`` and ``.h``,
``runtime_c/src/fbgf_contract.c``, the parameter table of ``docs/model-format.md`` and the
status constants of the ROS 2 message ``Contact.msg``; ``python -m fbgforce.contract --write``
writes them (:mod:`fbgforce.contract.__main__`)."""
from __future__ import annotations

import textwrap
from pathlib import Path

# The tables are read through the module, so that a kind added to contract.MEMORY_KINDS at run
# time (tests/test_contract.py) reaches the generator too.
from fbgforce import contract



ROOT = Path(__file__).resolve().parents[2]
HEADER_PATH = ROOT / "runtime_c" / "include" / "fbgforce.h"
SOURCE_PATH = ROOT / "runtime_c" / "src" / "fbg_contract.c"
SECTIONS = ("constants", "fixed", "state", "float", "float state")


def _begin(section: str) -> str:
    return (f"/* ---- BEGIN GENERATED {section}: `python -m fbgforce.contract --write` from "
            f"pkgroot/contract/; do not edit ---- */")


def _end(section: str) -> str:
    return f"/* ---- END GENERATED {section} ---- */"


def _decl(f: contract.Field, indent: str = "    ") -> str:
    arr = f"[{f.count}]" if f.count > 1 else ""
    rng = ""
    if f.lo is not None and (f.lo, f.hi) != contract.I32_RANGE:
        rng = f" [{f.lo}, {f.hi}]" + (f" for k < {f.active}, else 0" if f.active else "")
    doc = f"{f.doc}{rng}".strip()
    return f"{indent}{f.ctype} {f.name}{arr};" + (f"  /* {doc} */" if doc else "")


def struct_order(fields: tuple[contract.Field, ...]) -> list[contract.Field]:
    """Declaration order of a parameter struct: 4-byte fields, then 2, then 1 (no implicit
    padding). Generated initialisers list values in this order."""
    return [f for width in (4, 2, 1) for f in fields
            if contract.CTYPES[f.ctype][2] == width and f.c_member is None]


def struct_padding(fields: tuple[contract.Field, ...]) -> int:
    """Bytes of explicit padding (``pad_``) after the parameters of a struct."""
    return -sum(contract.CTYPES[f.ctype][2] * f.count for f in struct_order(fields)) % 4


def _struct_fields(fields: tuple[contract.Field, ...]) -> list[str]:
    out = [_decl(f) for f in struct_order(fields)]
    if struct_padding(fields):
        out.append(f"    uint8_t pad_[{struct_padding(fields)}];  /* explicit padding, keep 0 */")
    return out


def _comment(text: str, indent: str = "    ", width: int = 96) -> list[str]:
    """A block comment of ``text`` wrapped within ``width`` columns."""
    lines = textwrap.wrap(text, width - len(indent) - 6)
    out = [f"{indent}/* {lines[0]}"] + [f"{indent} * {line}" for line in lines[1:]]
    out[-1] += " */"
    return out


def _state_decl(f: contract.StateField) -> list[str]:
    dims = "".join(f"[{d}]" if isinstance(d, int) else f"[FBG_{d}]" for d in f.dims)
    decl = f"    {f.ctype}{'' if f.ctype.endswith('*') else ' '}{f.name}{dims};"
    return (_comment(f.note) if f.note else []) + [decl.ljust(48) + f" /* {f.doc} */" if f.doc else decl]


def state_section(fields: tuple[contract.StateField, ...], name: str) -> str:
    """The declaration of the streaming state ``name`` from its ``fields``."""
    return "\n".join([f"/* Caller-owned streaming state. Treat as opaque; size is sizeof({name}). */",
                      "typedef struct {"] + [line for f in fields for line in _state_decl(f)]
                     + [f"}} {name};"])


def header_sections() -> dict[str, str]:
    """The generated parts of fbgforce.h, by section name."""
    c = []
    for name, (value, doc) in contract.LIMITS.items():
        c.append(f"#define FBG_{name} {value}" + (f"  /* {doc} */" if doc else ""))
    for i, net in enumerate(contract.NETS):
        c.append(f"#define FBG_NET_{net.name.upper()} {i}")
    c += ["", "/* Return codes: 0 is success, every error has its own negative code. */",
          "typedef enum {"]
    for i, code in enumerate(contract.ERRORS):
        comma = "," if i + 1 < len(contract.ERRORS) else ""
        c.append(f"    FBG_{code.name} = {code.value}{comma}  /* {code.doc} */")
    c += ["} fbg_status;", "", "/* Output status flags (fbg_output.status; several may be set). */"]
    for code in contract.STATUS:
        c.append(f"#define FBG_STATUS_{code.name} 0x{code.value:02X}  /* {code.doc} */")
    c.append(f"#define FBG_STATUS_ALL 0x{contract.STATUS_ALL:02X}  /* every flag above: no other bit is ever set */")
    c += ["", "/* fbg_init options: flags, and one FBG_OPT_KERNEL_* value. */"]
    for code in contract.OPTIONS:
        c.append(f"#define FBG_OPT_{code.name} 0x{code.value:02X}  /* {code.doc} */")

    x = ["/* Fixed-point model. The parameters are those of the blob (docs/model-format.md),",
         " * declared grouped by size so that the struct has no implicit padding. */",
         "typedef struct {"]
    x += _struct_fields(contract.PARAMS)
    x += ["    const int16_t *taps;     /* n_taps FIR taps in Q(tap_q), taps[k] weights n - k */",
          "    fbg_net nets[FBG_N_NETS];",
          "    uint32_t blob_crc;       /* the blob's CRC-32 (fbg_model_from_blob, generated C); a state",
          "                              * refuses to step when it differs from fbg_init's */",
          "} fbg_model;", "",
          "/* Per-sample result of the fixed-point pipeline. When contact == 0: force_mN =",
          " * x_um = y_um = 0. Safe output (SENSOR_FAULT, or an error return): all 0 but status. */",
          "typedef struct {"]
    x += [_decl(f) for f in contract.OUTPUT]
    x += ["} fbg_output;"]

    fl = ["/* Float model: the same pipeline in single precision. */", "typedef struct {"]
    fl += _struct_fields(contract.FLOAT_PARAMS)
    fl += ["    const float *taps;       /* taps[k] weights sample n - k */",
           "    fbgf_net nets[FBG_N_NETS];   /* contact net has 2 outputs (logits) */",
           "} fbgf_model;", "", "typedef struct {"]
    fl += [_decl(f) for f in contract.FLOAT_OUTPUT]
    fl += ["} fbgf_output;"]
    return {"constants": "\n".join(c), "fixed": "\n".join(x),
            "state": state_section(contract.STATE, "fbg_state"), "float": "\n".join(fl),
            "float state": state_section(contract.FLOAT_STATE, "fbgf_state")}


def render_header(text: str) -> str:
    """``text`` (fbgforce.h) with every generated section replaced by the spec's."""
    for name, body in header_sections().items():
        start = text.index(_begin(name))
        end = text.index(_end(name)) + len(_end(name))
        text = text[:start] + _begin(name) + "\n" + body + "\n" + _end(name) + text[end:]
    return text


def _range_condition(f: contract.Field) -> str:
    """C condition of "v is outside [lo, hi]", without comparisons the type makes constant
    (-Wtype-limits)."""
    if f.lo is None:
        return "0"
    tmin, tmax = contract.CTYPE_RANGE[f.ctype]
    parts = []
    if f.lo > tmin:
        parts.append(f"v < {f.lo}")
    if f.hi < tmax:
        parts.append(f"v > {f.hi}")
    return " || ".join(parts) or "0"


def _params_check_lines() -> list[str]:
    """The body of ``fbg_params_check``: every range of ``PARAMS`` in blob order, the entries of
    an array past its ``active`` count held at 0."""
    out: list[str] = []
    for f in contract.PARAMS:
        if f.lo is None and not f.active:
            continue
        cond = _range_condition(f)
        if f.count == 1:
            out.append(f"    {{ {f.ctype} v = m->{f.c_lvalue()}; if ({cond}) return FBG_{f.code}; }}")
        elif f.active:
            out.append(f"    for (k = 0; k < {f.count}u; ++k) {{")
            out.append(f"        {f.ctype} v = m->{f.c_lvalue()};")
            out.append(f"        if (k >= (unsigned)m->{f.active}) {{")
            out.append("            if (v != 0)")
            out.append("                return FBG_ERR_RANGE;")
            out.append(f"        }} else if ({cond}) {{")
            out.append(f"            return FBG_{f.code};")
            out.append("        }")
            out.append("    }")
        else:
            out.append(f"    for (k = 0; k < {f.count}u; ++k) {{")
            out.append(f"        {f.ctype} v = m->{f.c_lvalue()};")
            out.append(f"        if ({cond})")
            out.append(f"            return FBG_{f.code};")
            out.append("    }")
    return out


def source_text() -> str:
    """runtime_c/src/fbg_contract.c: parameter decoder, checker and status names."""
    out = [
        "/*",
        " * fbg_contract.c - GENERATED by `python -m fbgforce.contract --write` from",
        " * pkgroot/contract/; do not edit. The blob parameter block decoder, the parameter",
        " * range checker (the same rules, in the same order, as fbgforce.contract.check_params)",
        " * and the names of the return codes.",
        " */",
        '#include "fbg_contract.h"', "",
        "static int32_t rd_i32(const uint8_t *p)",
        "{",
        "    uint32_t u = (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);",
        "    /* Two's-complement reinterpretation without implementation-defined conversion. */",
        "    return (u & 0x80000000u) ? -(int32_t)(~u) - 1 : (int32_t)u;",
        "}", "",
        "static uint32_t rd_u32(const uint8_t *p)",
        "{",
        "    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);",
        "}", "",
        "static uint16_t rd_u16(const uint8_t *p)",
        "{",
        "    return (uint16_t)(p[0] | (p[1] << 8));",
        "}", "",
        "static int16_t rd_i16(const uint8_t *p)",
        "{",
        "    uint16_t u = rd_u16(p);",
        "    return (u & 0x8000u) ? (int16_t)(-(int32_t)(uint16_t)~u - 1) : (int16_t)u;",
        "}", "",
        "static uint8_t rd_u8(const uint8_t *p)",
        "{",
        "    return p[0];",
        "}", "",
        "void fbg_params_decode(fbg_model *m, const uint8_t *p)",
        "{",
        "    unsigned k;",
        "    (void)k;",
    ]
    reader = {"int32_t": "rd_i32", "uint32_t": "rd_u32", "uint16_t": "rd_u16",
              "int16_t": "rd_i16", "uint8_t": "rd_u8"}
    off = 0
    for f in contract.PARAMS:
        size = contract.CTYPES[f.ctype][2]
        rd = reader[f.ctype]
        if f.count == 1:
            out.append(f"    m->{f.c_lvalue()} = {rd}(p + {off});")
        else:
            out.append(f"    for (k = 0; k < {f.count}u; ++k)")
            out.append(f"        m->{f.c_lvalue()} = {rd}(p + {off} + {size}u * k);")
        off += size * f.count
    out += ["}", "", "int fbg_params_padding_ok(const uint8_t *p)", "{",
            "    unsigned k;",
            f"    for (k = {contract.PARAMS_STRUCT.size}u; k < {contract.PARAMS_SIZE}u; ++k)",
            "        if (p[k] != 0u)", "            return 0;", "    return 1;", "}", "",
            "fbg_status fbg_params_check(const fbg_model *m)", "{", "    unsigned k;", "    (void)k;"]
    out += _params_check_lines()
    out += ["    return FBG_OK;", "}", "", "const char *fbg_status_str(int status)", "{",
            "    switch (status) {"]
    for c in contract.ERRORS:
        out.append(f"    case FBG_{c.name}: return \"FBG_{c.name}\";")
    out += ["    default: return \"FBG_ERR_UNKNOWN\";", "    }", "}", ""]
    return "\n".join(out)


def contract_header_text() -> str:
    """runtime_c/src/fbg_contract.h (internal): declarations of the generated functions."""
    return "\n".join([
        "/* fbg_contract.h - GENERATED by `python -m fbgforce.contract --write`; do not edit. */",
        "#ifndef FBG_CONTRACT_H", "#define FBG_CONTRACT_H", "", '#include "fbgforce.h"', "",
        f"#define FBG_PARAMS_SIZE {contract.PARAMS_SIZE}u     /* parameter block bytes, zero-padded */",
        f"#define FBG_PARAMS_END {contract.PARAMS_END}u      /* header + parameter block */",
        f"#define FBG_LAYER_ENTRY {contract.LAYER_ENTRY.size}u       /* bytes per layer-table entry */",
        "",
        "/* The memory states of a streaming state, X(s, member) each: the arrays of the memory",
        " * kinds and the location averages (fbg_state and fbgf_state name them alike; fbg_front.h",
        " * clears them on reset, tare and a new baseline). */",
        "#define FBG_MEMORY_STATES(X, s) " + " ".join(f"X(s, {m})" for m in contract.MEMORY_STATES),
        f"#define FBG_N_MEMORY_STATES {len(contract.MEMORY_STATES)}",
        "",
        "/* The memory kinds (fbgforce.contract.MEMORY_KINDS) in feature order, X(kind, KIND) each:",
        " * each engine reaches a kind's update rule by its name (fbg_stage_memory.c <kind>_features, ...). */",
        "#define FBG_MEMORY_KINDS(X) " + " ".join(f"X({k.name}, {k.name.upper()})" for k in contract.MEMORY_KINDS),
        "/* Memory features of a model (fbg_model or fbgf_model): one per state in use, every kind. */",
        "#define FBG_N_MEMORY_FEATURES(m) (" + " + ".join(
            ["(unsigned)(m)->" + contract.MEMORY_KINDS[0].count_field] + [f"(m)->{k.count_field}" for k in contract.MEMORY_KINDS[1:]])
        + ")",
        "",
        "/* Fill the parameter fields of *m from the block at p (PARAMS_SIZE bytes). */",
        "void fbg_params_decode(fbg_model *m, const uint8_t *p);",
        "/* 1 if the block's padding bytes are all zero. */",
        "int fbg_params_padding_ok(const uint8_t *p);",
        "/* The first parameter out of its range, in blob order: its code; else FBG_OK. */",
        "fbg_status fbg_params_check(const fbg_model *m);",
        "/* The float model's memory parameters (fbgf_contract.c): FBG_ERR_SHAPE for a count above",
        " * its limit, FBG_ERR_RANGE for a parameter of a state in use outside fbg_model's range",
        " * (a value in standardised units: negative or not finite); else FBG_OK. */",
        "fbg_status fbgf_memory_check(const fbgf_model *m);", "",
        "#endif /* FBG_CONTRACT_H */", ""])


FLOAT_SOURCE_PATH = SOURCE_PATH.with_name("fbgf_contract.c")


def float_source_text() -> str:
    """runtime_c/src/fbgf_contract.c: the float model's memory parameter checker (a float
    source: the fixed-point sources name no float type)."""
    out = ["/*",
           " * fbgf_contract.c - GENERATED by `python -m fbgforce.contract --write` from",
           " * pkgroot/contract/; do not edit. The float model's memory parameters checked against",
           " * the ranges of fbg_model's (fbgforce.contract.MEMORY_KINDS).",
           " */",
           '#include "fbg_contract.h"', "",
           "fbg_status fbgf_memory_check(const fbgf_model *m)", "{", "    unsigned k;"]
    out.append("    if (" + " || ".join(f"m->{k.count_field} > FBG_MAX_{k.name.upper()}"
                                        for k in contract.MEMORY_KINDS) + ")")
    out.append("        return FBG_ERR_SHAPE;")
    for kind in contract.MEMORY_KINDS:
        out.append(f"    for (k = 0; k < m->{kind.count_field}; ++k) {{")
        for prm in kind.params:
            cond = (f"!(v >= {prm.lo}.0f) || v - v != 0.0f" if prm.standardised  # NaN, inf
                    else _range_condition(contract.Field(prm.name, prm.float_ctype, 1, prm.lo, prm.hi)))
            out.append(f"        {{ {prm.float_ctype} v = m->{kind.field(prm)}[k]; "
                       f"if ({cond}) return FBG_ERR_RANGE; }}")
        out.append("    }")
    out += ["    return FBG_OK;", "}", ""]
    return "\n".join(out)


#: The ROS 2 estimate message; its status constants are generated from STATUS and LINK_STATUS.
CONTACT_MSG_PATH = ROOT / "interrogator" / "fbgforce_msgs" / "msg" / "Contact.msg"
MSG_BEGIN = "# BEGIN GENERATED status flags: `python -m fbgforce.contract --write`; do not edit"
MSG_END = "# END GENERATED status flags"
DOC_PATH = ROOT / "docs" / "model-format.md"
DOC_BEGIN = "<!-- BEGIN GENERATED params: `python -m fbgforce.contract --write`; do not edit -->"
DOC_END = "<!-- END GENERATED params -->"


def params_table() -> str:
    """The parameter block as a Markdown table (docs/model-format.md)."""
    rows = ["| offset | type | field | allowed | else |", "|---|---|---|---|---|"]
    off = contract.HEADER.size
    for f in contract.PARAMS:
        size = contract.CTYPES[f.ctype][2]
        typ = f"{f.ctype}[{f.count}]" if f.count > 1 else f.ctype
        allowed = "any" if f.lo is None else f"{f.lo} .. {f.hi}"
        if f.active:
            allowed += f" (entries from `{f.active}` on: 0)"
        doc = f.doc.replace("|", "\\|")
        rows.append(f"| {off} | {typ} | `{f.name}`: {doc} | {allowed} | "
                    f"{'' if f.lo is None and not f.active else 'FBG_' + f.code} |")
        off += size * f.count
    rows.append(f"| {off} | | zero padding to {contract.PARAMS_END} | 0 | FBG_ERR_RANGE |")
    return "\n".join(rows)


def render_doc(text: str) -> str:
    start = text.index(DOC_BEGIN)
    end = text.index(DOC_END) + len(DOC_END)
    return text[:start] + DOC_BEGIN + "\n" + params_table() + "\n" + DOC_END + text[end:]


def status_constants_msg() -> str:
    """The status flags as ROS 2 ``.msg`` constants (``uint32 STATUS_<NAME>=<value>``)."""
    rows = []
    for c in contract.STATUS + contract.LINK_STATUS:
        # The comment on a line of its own: parsers differ on comments after a constant.
        rows += [f"# {c.doc}", f"uint32 STATUS_{c.name}={c.value}"]
    return "\n".join(rows)


def render_msg(text: str) -> str:
    start = text.index(MSG_BEGIN)
    end = text.index(MSG_END) + len(MSG_END)
    return text[:start] + MSG_BEGIN + "\n" + status_constants_msg() + "\n" + MSG_END + text[end:]


def generated_files() -> dict[Path, str]:
    """Every generated file and its expected full text."""
    return {HEADER_PATH: render_header(HEADER_PATH.read_text()),
            DOC_PATH: render_doc(DOC_PATH.read_text()),
            CONTACT_MSG_PATH: render_msg(CONTACT_MSG_PATH.read_text()),
            SOURCE_PATH: source_text(),
            SOURCE_PATH.with_suffix(".h"): contract_header_text(),
            FLOAT_SOURCE_PATH: float_source_text()}


def stale_files() -> list[Path]:
    """Generated files whose text differs from what the spec gives."""
    return [p for p, t in generated_files().items() if not p.is_file() or p.read_text() != t]
