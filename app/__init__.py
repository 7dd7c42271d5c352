"""The salad studio: a Gradio UI over `salad.pipeline` and `salad.render`.

`python -m app` starts it (see `app.cli`). The studio runs offline: importing this
package switches off Gradio analytics and model-hub look-ups unless the caller has
set those variables already, and torch's OpenMP threads wait as `salad` sets them.
"""
import os

import salad  # noqa: F401  (before any module here loads torch: it sets how OpenMP threads wait)

for _key, _value in (("GRADIO_ANALYTICS_ENABLED", "False"), ("HF_HUB_OFFLINE", "1"),
                     ("HF_HUB_DISABLE_TELEMETRY", "1"), ("TRANSFORMERS_OFFLINE", "1")):
    os.environ.setdefault(_key, _value)
