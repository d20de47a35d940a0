"""The three evolved expressions of Davletaliyev 2016 (Sec. 4.4, Eq. 4.1-4.8) and the bilateral seed.

Transcribed from the thesis's typeset formulas, with these readings (the equations are typeset as fractions
and superscripts; where the layout leaves a choice, the reading that gives an edge-stopping weight, i.e.
one that falls with the spatial distance and the feature differences, is taken; tests pin each reading):

- |f_i . f_j| is the dot product (the grammar has no absolute value; all dot products in the three
  expressions are of non-negative features, texture and colour, where |.| changes nothing).
- ||x||^2_{L2} is pow(distance2, 2.0); a superscript on a constant is pow of constants (0.1^3 in Eq. 4.3,
  2^3 in Eq. 4.7), which the grammar builds from its constants 0.1, 2.0, 3.0.
- Eq. 4.1: biweight(-((||di||^2)^2 * 2)), "* 2" as printed.
- Eq. 4.3: exp(-(A * B)) with A = (||di||_L1 ||di||_max)^power cos(exp(-||n||^2 / 0.1^3)) + t_i.t_j and
  B = ||p||_L1 - atan(-||n||_L1): the two parenthesised factors are a product (a quotient would let the
  weight grow with the spatial distance).
- Eq. 4.4: power = 2 + biweight(sqrt(||wpg||_L2 ||p||_L2 / (0.01 + ||wp||_L1))), the square root over the
  whole fraction. The other reading (the typeset brackets closing biweight after 0.01, then
  "+ ||wp||_L1" added to the power) is written out in conf/model/gp_expr2.yaml; the text does not decide.
- Eq. 4.6: exp(-(||p||_L1 + 2 + e^(e^(sinc(||wp||^0.002)))) / (2 asin(biweight(((||n|| / 2)^power1)^power2))))
  with the "2 asin(...)" under the fraction bar (as a factor it would make opposite normals weigh *more*), and
  "||n||_{L2} 2" as ||n|| / 2 (every squared norm in the thesis prints its exponent before the subscript).
- Eq. 4.7: power1 = e^(biweight(||c||_max / (2^3 sinc(||di||_L2)))).
- Eq. 4.8: power2 = e^(-||t||^2_max / 0.01) * e^(tricube(||di||_L2) mitchell(var_wp)).
- var_wp (wpVariance) is the world-position variance of the centre pixel.

Features each expression reads (`src.gp.evaluate.required_terminals`):
    EXPR1: color depth directIllumination normal texture
    EXPR2: color directIllumination normal pixel texture worldPosition wpGradient
    EXPR3: color directIllumination normal pixel texture worldPosition wpVariance
"""

from __future__ import annotations

import math

EXPR1 = (
    "exp(-(distance2(depth, depth) + distance2(normal, normal) + 2.0 * dot(texture, texture)"
    " + distance2(color, color) + distanceMax(texture, texture) + distance1(normal, normal)))"
    " * biweight(-((distance2(directIllumination, directIllumination) ** 2.0) ** 2.0 * 2.0))"
)
"""Davletaliyev 2016, Eq. 4.1 (trained on 3 PBRT scenes)."""

_POWER = (
    "(2.0 + biweight(sqrt(distance2(wpGradient, wpGradient) * distance2(pixel, pixel)"
    " / (0.01 + distance1(worldPosition, worldPosition)))))"
)
EXPR2 = (
    "exp(-atan(dot(color, color))) * exp(-(((distance1(directIllumination, directIllumination)"
    " * distanceMax(directIllumination, directIllumination)) ** " + _POWER + ""
    " * cos(exp(-(distance2(normal, normal) ** 2.0 / 0.1 ** 3.0))) + dot(texture, texture))"
    " * (distance1(pixel, pixel) - atan(-distance1(normal, normal)))))"
)
"""Davletaliyev 2016, Eq. 4.2-4.4 (trained on all 6 scenes)."""

_POWER1 = (
    "exp(biweight(distanceMax(color, color)"
    " / (2.0 ** 3.0 * sinc(distance2(directIllumination, directIllumination)))))"
)
_POWER2 = (
    "(exp(-(distanceMax(texture, texture) ** 2.0 / 0.01))"
    " * exp(tricube(distance2(directIllumination, directIllumination)) * mitchell(wpVariance)))"
)
EXPR3 = (
    "exp(-(distanceMax(worldPosition, worldPosition) / 0.05)) * exp(-((distance1(pixel, pixel) + 2.0"
    " + exp(exp(sinc(distance2(worldPosition, worldPosition) ** 0.002))))"
    " / (2.0 * asin(biweight(((distance2(normal, normal) / 2.0) ** " + _POWER1 + ") ** " + _POWER2 + ")))))"
)
"""Davletaliyev 2016, Eq. 4.5-4.8 (trained on all 6 scenes)."""

PUBLISHED = {"gp_expr1": EXPR1, "gp_expr2": EXPR2, "gp_expr3": EXPR3}


def bilateral_expression(
    sigma_spatial: float,
    sigma_color: float,
    sigma_normal: float,
    sigma_albedo: float,
    sigma_depth: float,
) -> str:
    """The cross-bilateral filter as an expression, the seed of the thesis's population (Sec. 3.2.5):

        exp(-(||p_i - p_j||^2 / 2 s_spatial^2 + ||c_i - c_j||^2 / 2 s_color^2 + ||n_i - n_j||^2 / 2 s_normal^2
              + ||t_i - t_j||^2 / 2 s_albedo^2 + ||d_i - d_j||^2 / 2 s_depth^2))

    the weight of `src.models.filters.cross_bilateral` (which feeds log(1 + c) as the colour feature). An
    infinite sigma drops its term; each 2 s^2 is one constant.
    """
    sigmas = {
        "pixel": sigma_spatial,
        "color": sigma_color,
        "normal": sigma_normal,
        "texture": sigma_albedo,
        "depth": sigma_depth,
    }
    terms = []
    for name, sigma in sigmas.items():
        if not float(sigma) > 0:
            raise ValueError(f"sigma of {name} must be > 0, got {sigma!r}")
        if math.isinf(sigma):
            continue
        terms.append(f"distance2({name}, {name}) ** 2.0 / {2.0 * float(sigma) ** 2!r}")
    if not terms:
        return "1.0"
    return f"exp(-({' + '.join(terms)}))"
