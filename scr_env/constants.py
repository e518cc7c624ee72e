"""Physical constants and AdBlue chemistry, each with its unit and source."""
from __future__ import annotations

GAS_CONSTANT_J_MOL_K: float = 8.314462618  # J/(mol K), CODATA 2018
ATMOSPHERIC_PRESSURE_PA: float = 101_325.0  # Pa; the SCR runs close to 1 atm [chosen: back-pressure neglected]
EXHAUST_MOLAR_MASS_KG_MOL: float = 0.0289  # kg/mol, lean diesel exhaust ~ air [lit: Heywood 1988, ch. 4]
EXHAUST_HEAT_CAPACITY_J_KG_K: float = 1250.0  # J/(kg K) [lit: LiU 2018 heavy-duty aftertreatment model, PHYSICS.md]
AMBIENT_TEMPERATURE_K: float = 298.15  # K, test-cell ambient [chosen: 25 C]

# AdBlue (AUS 32, ISO 22241-1): 32.5 wt% urea in water.
ADBLUE_UREA_MASS_FRACTION: float = 0.325  # kg urea / kg AdBlue [ISO 22241-1]
ADBLUE_DENSITY_KG_M3: float = 1090.0  # kg/m3 at 20 C [ISO 22241-1]
UREA_MOLAR_MASS_KG_MOL: float = 0.06006  # kg/mol, CO(NH2)2
NH3_PER_UREA: float = 2.0  # mol NH3 per mol urea (thermolysis to NH3 + HNCO, then HNCO hydrolysis)
NH3_MOLAR_MASS_G_MOL: float = 17.031  # g/mol
NO2_MOLAR_MASS_G_MOL: float = 46.0055  # g/mol; NOx mass is reported as NO2 equivalent (Regulation 49)
N2O_MOLAR_MASS_G_MOL: float = 44.013  # g/mol
# mol NH3 released by one gram of AdBlue after full decomposition: 0.325 / 60.06 * 2 = 0.010823 mol/g (PHYSICS.md 3)
NH3_MOL_PER_G_ADBLUE: float = ADBLUE_UREA_MASS_FRACTION / (UREA_MOLAR_MASS_KG_MOL * 1000.0) * NH3_PER_UREA

# Unit factors and regulatory limits used by the controllers and experiments (one definition each).
SECONDS_PER_MINUTE: float = 60.0  # s/min
# g/min of urea per g/s of AdBlue: 60 s/min * 0.325 g urea / g AdBlue = 19.5 (the unit of the thesis' u2)
UREA_G_MIN_PER_ADBLUE_G_S: float = SECONDS_PER_MINUTE * ADBLUE_UREA_MASS_FRACTION
# Euro VI mean NH3 slip limit over the WHTC/WHSC [ppm] [Regulation (EU) No 582/2011, Annex I, 10 ppm]
EURO_VI_NH3_SLIP_LIMIT_PPM: float = 10.0
