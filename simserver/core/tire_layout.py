"""Slot layout shared by every tire model: the common parameter slots and the outputs.

Kept apart from :mod:`simserver.core.tire` so that each model kernel can import it
without importing the dispatcher.
"""

# --- model ids (tp[TP_MODEL]) -----------------------------------------------------
TIRE_MODEL_SIMPLE = 0  # brush-type (Fiala) combined-slip model, explicit stiffnesses
TIRE_MODEL_MF61 = 1  # Magic Formula 6.1 from a .tir property file
TIRE_MODEL_NAMES = {"simple": TIRE_MODEL_SIMPLE, "mf61": TIRE_MODEL_MF61}

# --- common parameter slots --------------------------------------------------------
TP_MODEL = 0
TP_RADIUS_M = 1  # effective rolling radius R (m)
TP_RELAX_LAT_M = 2  # lateral relaxation length b (m), paper eq. 16
TP_RELAX_LONG_M = 3  # longitudinal relaxation length B (m), paper eq. 26
TP_MODEL_BASE = 4  # first model-specific slot

# --- outputs ---------------------------------------------------------------------
OUT_FX = 0  # longitudinal force (N), wheel frame
OUT_FY = 1  # lateral force (N), wheel frame
OUT_MZ = 2  # aligning moment (N m)
OUT_MY = 3  # rolling-resistance moment magnitude (N m, >= 0), applied against spin
OUT_C_KAPPA = 4  # longitudinal slip stiffness dFx/dkappa at kappa = 0 (N per unit slip)
OUT_C_ALPHA = 5  # cornering stiffness -dFy/dtan_alpha at 0 (N/rad, > 0)
OUT_KAPPA_SLIDE = 6  # |kappa| at the peak of pure-slip Fx: the sliding limit (> 0)
OUT_TAN_ALPHA_SLIDE = 7  # |tan alpha| at the peak of pure-slip Fy: the sliding limit (> 0)
OUT_FX_PEAK = 8  # peak pure-slip |Fx| at this load and friction (N)
OUT_FY_PEAK = 9  # peak pure-slip |Fy| at this load and friction (N)
N_TIRE_OUT = 10
