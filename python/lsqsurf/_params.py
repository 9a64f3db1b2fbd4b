"""Keyword parameters checked against the server's own tables (ListMethods) before anything is sent,
and written in the text form the client library sets them from."""
import math
import numbers


def _describe(p):
    kind = p["type"]
    if kind == "TYPE_CHOICE":
        return "one of " + ", ".join(c["name"] for c in p.get("choices", []))
    if kind == "TYPE_FLAG":
        return "True or False"
    if kind in ("TYPE_REAL", "TYPE_INTEGER", "TYPE_REAL_LIST"):
        text = f"[{float(p['min_value']):g}, {float(p['max_value']):g}]"
        special = [f"{float(s['value']):g} ({s['meaning']})" for s in p.get("special_values", [])]
        if kind == "TYPE_REAL_LIST":
            text = f"up to {p.get('max_count', 0)} numbers, each in {text}"
        return " or ".join(special + [text])
    return "text"


def _in_range(p, value):
    if any(value == float(s["value"]) for s in p.get("special_values", [])):
        return True
    # float(): JSON writes an infinite bound as the text "Infinity".
    return float(p["min_value"]) <= value <= float(p["max_value"])


def _number(method, name, p, value):
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{method} parameter '{name}' must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or not _in_range(p, value):
        raise ValueError(f"{method} parameter '{name}' = {value:g} is out of range: {_describe(p)}")
    return value


def text_of(method, name, p, value):
    """The checked value as the text the client library reads. Raises ValueError naming the
    parameter and what it accepts."""
    kind = p["type"]
    if kind == "TYPE_REAL":
        return repr(_number(method, name, p, value))
    if kind == "TYPE_INTEGER":
        number = _number(method, name, p, value)
        if number != int(number):
            raise ValueError(f"{method} parameter '{name}' must be a whole number, got {value!r}")
        return str(int(number))
    if kind == "TYPE_FLAG":
        if value not in (True, False):  # 0 and 1 compare equal to False and True
            raise ValueError(f"{method} parameter '{name}' must be True or False, got {value!r}")
        return "true" if value else "false"
    if kind == "TYPE_CHOICE":
        names = [c["name"] for c in p.get("choices", [])]
        if not isinstance(value, str) or value.lower() not in names:
            raise ValueError(f"{method} parameter '{name}' = {value!r} is not {_describe(p)}")
        return value.lower()
    if kind == "TYPE_REAL_LIST":
        values = [value] if isinstance(value, numbers.Real) else list(value)
        if len(values) > p.get("max_count", 0):
            raise ValueError(f"{method} parameter '{name}' takes {_describe(p)}; got {len(values)}")
        return ",".join(repr(_number(method, name, p, v)) for v in values)
    if not isinstance(value, str):
        raise ValueError(f"{method} parameter '{name}' must be text, got {value!r}")
    return value


def check(methods, method, params):
    """(name, text) pairs for `params` of `method`; `methods` is the server's table by name."""
    if method not in methods:
        raise ValueError(f"unknown method '{method}'; the server offers: {', '.join(sorted(methods))}")
    table = {p["name"]: p for p in methods[method].get("parameters", [])}
    pairs = []
    for name, value in params.items():
        if value is None:
            continue  # Not given: the server's default.
        if name not in table:
            raise ValueError(
                f"unknown parameter '{name}' for method {method}; valid parameters: {', '.join(table)}"
            )
        pairs.append((name, text_of(method, name, table[name], value)))
    return pairs
