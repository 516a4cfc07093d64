"""RGB -> thermal registration: one homography per inspection group, in one place.

A homography ``H`` maps an RGB pixel ``(x, y)`` to the thermal pixel ``(u, v)``::

    [u', v', w']^T = H [x, y, 1]^T,   (u, v) = (u' / w', v' / w')

It is obtained in one of four ways:

* **landmarks**: at least 4 pairs of clicked points, by least squares (``cv2.findHomography``, DLT +
  Levenberg-Marquardt on the reprojection error) or RANSAC against outliers (``fit_landmarks``, one
  ``LandmarkFit`` record with its quality fields);
* **similarity parameters** (the seed's interactive adjustment): translation ``(tx, ty)``, rotation ``theta`` and
  scale ``s`` about the image centres, ``u = s R(theta) (x - c_rgb) + c_thermal + t``;
* **the optics prior**: centres aligned, scale from the two cameras' focal lengths (``focal_prior``);
* **automatically** (``estimate_homography_auto``), from the prior or a given H, with a quality check.

==============  ===============================================================================================
module          what it holds
==============  ===============================================================================================
``homography``  ``apply_homography``, errors between homographies, similarity parameters, focal lengths and the
                prior, camera-frame changes, plane-induced homographies (also the synthetic generator's geometry)
``landmarks``   ``Landmarks`` files, ``fit_landmarks``/``fit_groups`` -> ``LandmarkFit``, registration error,
                leave-one-out error
``auto``        ``estimate_homography_auto`` (ECC on structure images) -> ``AutoRegistration``, ``register_files``
``files``       ``HomographyEntry`` and the editable homographies YAML
``groups``      inspection groups from capture times
``dataset``     ``DatasetRegistration``: a raw dataset's per-group policy (its file, its landmarks, the config's
                method), used by the dataset adapters; import it from its module
``truth``       registration error beside the true homographies (synthetic data)
==============  ===============================================================================================
"""

from __future__ import annotations

from harness.sensing.registration.auto import (
    AutoRegistration,
    ecc_correlation,
    estimate_homography_auto,
    optics_prior,
    read_image_rgb,
    read_thermal_any,
    register_files,
    structure_image,
)
from harness.sensing.registration.files import (
    HOMOGRAPHY_FILE_HEADER,
    HomographyEntry,
    entry_from_similarity,
    load_homographies,
    load_homography_entries,
    save_homographies,
    support_boxes,
)
from harness.sensing.registration.groups import capture_time, group_by_capture_time
from harness.sensing.registration.homography import (
    FULL_FRAME_DIAGONAL_MM,
    apply_homography,
    change_camera,
    corner_error,
    focal_length_px,
    focal_prior,
    homography_from_focal_lengths,
    homography_from_similarity,
    image_center,
    normalize,
    plane_homography,
    project_points,
    reprojection_errors,
    similarity_from_homography,
)
from harness.sensing.registration.landmarks import (
    LANDMARK_COLUMNS,
    LandmarkFit,
    Landmarks,
    fit_groups,
    fit_landmarks,
    homography_from_landmarks,
    leave_one_out_errors,
    read_landmarks,
    registration_error,
    write_landmarks,
)

__all__ = [
    "AutoRegistration",
    "ecc_correlation",
    "estimate_homography_auto",
    "optics_prior",
    "read_image_rgb",
    "read_thermal_any",
    "register_files",
    "structure_image",
    "HOMOGRAPHY_FILE_HEADER",
    "HomographyEntry",
    "entry_from_similarity",
    "load_homographies",
    "load_homography_entries",
    "save_homographies",
    "support_boxes",
    "capture_time",
    "group_by_capture_time",
    "FULL_FRAME_DIAGONAL_MM",
    "apply_homography",
    "change_camera",
    "corner_error",
    "focal_length_px",
    "focal_prior",
    "homography_from_focal_lengths",
    "homography_from_similarity",
    "image_center",
    "normalize",
    "plane_homography",
    "project_points",
    "reprojection_errors",
    "similarity_from_homography",
    "LANDMARK_COLUMNS",
    "LandmarkFit",
    "Landmarks",
    "fit_groups",
    "fit_landmarks",
    "homography_from_landmarks",
    "leave_one_out_errors",
    "read_landmarks",
    "registration_error",
    "write_landmarks",
]
