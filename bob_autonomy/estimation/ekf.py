"""The buoy and eBot EKFs under their former module name: re-exports of bob_autonomy.estimation (see there)."""

from bob_autonomy.estimation import (
    CHI2_999,
    OUTCOMES,
    BuoyEkf,
    BuoyEkfBank,
    BuoyEkfParams,
    EbotEkf,
    EbotEkfBank,
    EbotEkfParams,
    kalman_predict_rows,
    kalman_update_rows,
    wrap_angle,
)

__all__ = [
    "CHI2_999",
    "OUTCOMES",
    "BuoyEkf",
    "BuoyEkfBank",
    "BuoyEkfParams",
    "EbotEkf",
    "EbotEkfBank",
    "EbotEkfParams",
    "kalman_predict_rows",
    "kalman_update_rows",
    "wrap_angle",
]
