from armfit import Effect, Param


def _spring(s, values, mp):
    return values["k_N_per_m"] + 0.0 * s


def _spring_rational(values, mp):
    return values["k_N_per_m"], 1.0      # k/1: num(s) = k, den(s) = 1


EFFECTS = [Effect(
    name="device-spring", stage="device",
    params=(Param("k_N_per_m", "N/m", 0.01, 5000.0, 50.0, "spring in the device"),),
    term=_spring, rational=_spring_rational,
    summary="A spring in the device: its impedance gains k.", null=(0.01,))]
