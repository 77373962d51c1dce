"""Watch and steer a networked run live in a browser (``virtual-vehicle view SCENARIO``), or replay a finished one
from its run folder (``virtual-vehicle view RUN_FOLDER``).

:mod:`.live` is the run under the viewer and the record of what was done to it; :mod:`.server` the Bokeh server
that serves the page with an access token; :mod:`.page` the live page; :mod:`.replay` a run folder read back and
its page, with a time scrubber; :mod:`.draw` what both pages draw.
"""

from virtual_vehicle.ui.view.live import COLOUR_BY, STILL, LiveRun
from virtual_vehicle.ui.view.page import SPEEDS
from virtual_vehicle.ui.view.server import LOOPBACK, Viewer

__all__ = ["COLOUR_BY", "LOOPBACK", "SPEEDS", "STILL", "LiveRun", "Viewer"]
