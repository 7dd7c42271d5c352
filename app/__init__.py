"""The salad studio: a Gradio UI over `salad.pipeline` and `salad.render`.

`python -m app` starts it (see `app.cli`). The studio runs offline: importing this
package switches off Gradio analytics and model-hub look-ups unless the caller has
set those variables already, and torch's OpenMP threads wait as `salad` sets them.
"""
# the first import of salad, before any module here loads torch: it sets how OpenMP threads wait
from salad.environment import use_offline_defaults

use_offline_defaults()
