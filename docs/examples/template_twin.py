"""A template twin: copy it and replace ``step`` with your simulator.

It speaks the twin protocol (version 1) on stdin/stdout with the standard library only:
one JSON request per line in, one JSON answer per line out, logs to stderr.
Check it with: python -m twinfalsify.runs.check --spec '{"kind": "command",
"command": "python docs/examples/template_twin.py"}'
"""

import json
import random
import sys

UNITS = {"age": "years", "sex": "0/1", "weight": "kg", "HR": "/min", "SysBP": "mmHg",
         "DiaBP": "mmHg", "MeanBP": "mmHg", "RR": "/min", "Temp_C": "degC",
         "Potassium": "mmol/L", "Sodium": "mmol/L", "Chloride": "mmol/L", "Glucose": "mg/dL",
         "Calcium": "mg/dL", "HCO3": "mmol/L", "paO2": "mmHg", "paCO2": "mmHg",
         "Arterial_pH": "pH"}


def step(x, iv, vaso, rng):
    """One hour of IV fluid (mL/h) and vasopressor (ug/kg/min): the state at its end."""
    x = dict(x)
    x["SysBP"] += 0.02 * iv + 25 * vaso + rng.gauss(0, 2)
    x["DiaBP"] += 0.01 * iv + 12 * vaso + rng.gauss(0, 1.5)
    x["MeanBP"] = (x["SysBP"] + 2 * x["DiaBP"]) / 3
    x["HR"] += -0.01 * iv + 8 * vaso + rng.gauss(0, 2)
    x["Chloride"] += 0.004 * iv  # saline
    return x


def simulate(request):
    x, hours = request["x0"], []
    for h, (iv, vaso) in enumerate(request["doses"][: request["hours"]]):
        # hour h's randomness from the seed and the doses of hours 1..h only, so runs that
        # share a dose prefix share its simulation
        rng = random.Random(f"{request['seed']}:{request['doses'][: h + 1]}")
        x = step(x, iv, vaso, rng)
        hours.append(x)
    return {"status": "ok", "message": "", "hours": hours, "clamped": {}}


for line in sys.stdin:
    if not line.strip():
        continue
    msg = json.loads(line)
    if msg["op"] == "hello":
        answer = {"op": "hello", "ok": True, "name": "template", "version": "1.0",
                  "protocol": 1, "capabilities": {},
                  "features": [{"name": k, "unit": u} for k, u in UNITS.items()]}
    elif msg["op"] == "simulate":
        try:
            answer = {"op": "result", "id": msg["id"], **simulate(msg)}
        except Exception as exc:  # a failed run is an answer, not a crash
            answer = {"op": "result", "id": msg["id"], "status": "error",
                      "message": repr(exc), "hours": [], "clamped": {}}
    elif msg["op"] == "shutdown":
        print(json.dumps({"op": "bye"}), flush=True)
        break
    else:
        answer = {"op": "error", "message": f"unknown op {msg['op']!r}"}
    print(json.dumps(answer), flush=True)
