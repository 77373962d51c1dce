"""virtual_vehicle: simulate and control distributed actuator arrays (Luntz, Messner & Choset, "Virtual Vehicle").

Units are SI throughout: m, s, kg, N, rad.
"""

__version__ = "0.1.0"

from virtual_vehicle import compiled_cache  # noqa: E402  (before any compiled function is defined: its cache folder)

compiled_cache.choose()

from virtual_vehicle.errors import IntegrationError, ScenarioError, TippingError, VirtualVehicleError  # noqa: E402

__all__ = ["__version__", "VirtualVehicleError", "ScenarioError", "TippingError", "IntegrationError"]
