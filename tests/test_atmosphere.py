"""Numerical clear sky (mvintrinsic.synth.atmosphere): physics, map convention, Mitsuba envmap."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mvintrinsic.envmap import direction_to_texel, envmap_directions
from mvintrinsic.files import import_colour
from mvintrinsic.synth.atmosphere import MITSUBA_ENVMAP_TO_WORLD, AtmosphereConfig, clear_sky, envmap_emitter
from mvintrinsic.synth.render import sun_vector

# Tolerances, in one place.
CLOSED_FORM_RTOL = 0.01  # numerical single scattering vs the plane-parallel closed form (seen: < 0.12 %)
MITSUBA_RTOL = 0.02  # Mitsuba-rendered radiance vs the map / vs sun_radiance (seen: < 1e-5)
GROUND_RTOL = 1e-3  # ground texels vs albedo / π (direct + sky irradiance of the map)
MS_FRACTION_RANGE = (0.05, 0.5)  # orders >= 2 over single scattering at the zenith, black ground

RAYLEIGH_ONLY = AtmosphereConfig(aerosol_scale=0.0, ozone_column=0.0, multiple_scattering=False, ground_albedo=0.0)


def luminance(rgb):
    return np.asarray(rgb, dtype=np.float64) @ [0.2126, 0.7152, 0.0722]


def blue_over_red(rgb):
    rgb = np.asarray(rgb, dtype=np.float64)
    return rgb[..., 2] / rgb[..., 0]


@pytest.fixture(scope="module")
def sky45():
    return clear_sky(sun_vector(0.0, 45.0), width=128)


@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'mvintrinsic[render]')")
    from mvintrinsic.synth.render import import_mitsuba

    return import_mitsuba()


# ------------------------------------------------------------------------------------------------
# Physics
# ------------------------------------------------------------------------------------------------
def planck_solar_irradiance(wavelengths_nm, temperature=5778.0, total=1361.0):
    """5778 K black body scaled to 1361 W m^-2 in total, W m^-2 nm^-1 (independent of the module)."""
    h, c, k, sigma = 6.62607015e-34, 2.99792458e8, 1.380649e-23, 5.670374419e-8
    lam = np.asarray(wavelengths_nm) * 1e-9
    radiance = 2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * temperature)) * 1e-9  # W m^-2 sr^-1 nm^-1
    return total * math.pi * radiance / (sigma * temperature**4)


def spectrum_to_rgb(wavelengths_nm, spectrum):
    """Linear sRGB of a spectrum taken linear between samples: CIE 1931 2° CMFs at 1 nm, IEC matrix."""
    colour = import_colour()
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    grid = np.arange(wavelengths_nm[0], wavelengths_nm[-1] + 0.5, 1.0)
    cmf = np.stack([np.interp(grid, cmfs.wavelengths, cmfs.values[:, i]) for i in range(3)], axis=1)
    weights = np.ones(len(grid))
    weights[[0, -1]] = 0.5
    xyz = (np.interp(grid, wavelengths_nm, spectrum) * weights) @ cmf
    return colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB @ xyz


def test_single_rayleigh_scattering_matches_the_plane_parallel_closed_form():
    # Sun at the zenith, pure Rayleigh air (no aerosol, ozone, ground or multiple scattering), view
    # at cos zenith μ. In a plane-parallel atmosphere of total optical depth τ, with a = optical
    # depth above the scattering point (sun ray, vertical) and (τ - a) / μ along the view ray:
    #   L = E0 P(μ) ∫_0^τ exp(-a) exp(-(τ - a) / μ) da / μ = E0 P(μ) (exp(-τ) - exp(-τ/μ)) / (1 - μ),
    # for any density profile (the integral runs over optical depth); P(μ) = 3 (1 + μ²) / 16π is the
    # Rayleigh phase at the scattering angle arccos μ, and τ = β_R H_R (1 - exp(-60 km / H_R)).
    # Near the zenith, the curvature of the Earth changes this by far less than 1 %.
    config = RAYLEIGH_ONLY
    sky = clear_sky([0.0, 0.0, 1.0], width=32, config=config)
    lam = config.wavelengths
    e0 = planck_solar_irradiance(lam)
    tau = config.rayleigh_scattering * (550.0 / lam) ** 4 * config.rayleigh_scale_height * (1 - math.exp(-60 / 8))
    for row in range(4):  # polar angles 5.6°, 16.9°, 28.1°, 39.4°
        mu = float(sky.direction_of_texel(row, 0)[2])
        phase = 3.0 / (16.0 * math.pi) * (1.0 + mu * mu)
        expected = spectrum_to_rgb(lam, e0 * phase * (np.exp(-tau) - np.exp(-tau / mu)) / (1.0 - mu))
        # Azimuthal symmetry about the zenith sun: every texel of the row is the same.
        np.testing.assert_allclose(sky.radiance[row], np.broadcast_to(sky.radiance[row, 0], (32, 3)), rtol=1e-5)
        np.testing.assert_allclose(sky.radiance[row, 0], expected, rtol=CLOSED_FORM_RTOL)


def test_radiance_is_finite_nonnegative_float32(sky45):
    assert sky45.radiance.shape == (64, 128, 3)
    assert sky45.radiance.dtype == np.float32
    assert np.isfinite(sky45.radiance).all() and (sky45.radiance >= 0).all()
    assert sky45.sun_radiance.shape == (3,) and sky45.sun_radiance.dtype == np.float64
    assert np.isfinite(sky45.sun_radiance).all() and (sky45.sun_radiance > 0).all()
    assert (sky45.radiance[:32] > 0).all()


def test_zenith_is_blue_and_bluer_than_the_horizon_below_the_sun(sky45):
    zenith = sky45.radiance[0].mean(axis=0)
    rows, cols = sky45.texel_of_direction(sun_vector(0.0, 2.0))  # just above the horizon, sun's azimuth
    near_sun_horizon = sky45.radiance[rows, cols]
    assert blue_over_red(zenith) > 1.0
    assert blue_over_red(zenith) > blue_over_red(near_sun_horizon)


def test_horizon_brighter_than_zenith_for_a_high_sun():
    sky = clear_sky(sun_vector(0.0, 60.0), width=128)
    zenith = luminance(sky.radiance[0]).mean()
    horizon = luminance(sky.radiance[31]).mean()  # elevation 0.7°, every azimuth
    assert horizon > 1.5 * zenith


def test_low_sun_is_redder_and_dimmer():
    low = clear_sky(sun_vector(0.0, 10.0), width=8).sun_radiance
    high = clear_sky(sun_vector(0.0, 60.0), width=8).sun_radiance
    assert blue_over_red(low) < blue_over_red(high)
    assert luminance(low) < luminance(high)


def test_multiple_scattering_adds_a_modest_positive_fraction_at_the_zenith():
    # With a black ground, orders >= 2 add 10 % (R) to 40 % (B) of single scattering at the zenith
    # for the clear default atmosphere, more at short wavelengths; a grey ground of albedo 0.3 adds
    # about as much again (its sunlit radiance scattered by the air).
    sun = sun_vector(0.0, 45.0)
    black = replace(AtmosphereConfig(), ground_albedo=0.0)
    single = clear_sky(sun, width=16, config=replace(black, multiple_scattering=False)).radiance[0].mean(axis=0)
    multiple = clear_sky(sun, width=16, config=black).radiance[0].mean(axis=0)
    fraction = multiple / single - 1.0
    assert (fraction > MS_FRACTION_RANGE[0]).all() and (fraction < MS_FRACTION_RANGE[1]).all()
    assert fraction[0] < fraction[1] < fraction[2]
    grey = clear_sky(sun, width=16).radiance[0].mean(axis=0)
    assert (grey > multiple).all()


def test_ground_texels_are_the_lambertian_ground_under_sun_and_sky(sky45):
    # Observer at 0 m: every texel below the horizon sees the ground at its feet, of radiance
    # albedo / π (π L_sun cos θ_sun + E_sky), E_sky = ∫ L cos θ dω over the upper half of the map.
    height, width = sky45.height, sky45.width
    edges = np.pi * np.arange(height // 2 + 1) / height
    row_weight = (2 * np.pi / width) * 0.5 * (np.sin(edges[1:]) ** 2 - np.sin(edges[:-1]) ** 2)
    sky_irradiance = np.einsum("vuc,v->c", sky45.radiance[: height // 2].astype(np.float64), row_weight)
    direct = np.pi * sky45.sun_radiance * sky45.sun_direction[2]
    expected = sky45.config.ground_albedo / np.pi * (direct + sky_irradiance)
    ground = sky45.radiance[height // 2 :].reshape(-1, 3)
    np.testing.assert_allclose(ground, np.broadcast_to(expected, ground.shape), rtol=GROUND_RTOL)


def test_deterministic(sky45):
    again = clear_sky(sun_vector(0.0, 45.0), width=128)
    np.testing.assert_array_equal(again.radiance, sky45.radiance)
    np.testing.assert_array_equal(again.sun_radiance, sky45.sun_radiance)


def test_scale_multiplies_everything(sky45):
    scaled = clear_sky(sun_vector(0.0, 45.0), width=128, scale=0.01)
    np.testing.assert_allclose(scaled.radiance, 0.01 * sky45.radiance, rtol=1e-5)
    np.testing.assert_allclose(scaled.sun_radiance, 0.01 * sky45.sun_radiance, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# Map convention
# ------------------------------------------------------------------------------------------------
def test_texel_direction_round_trip_and_project_convention(sky45):
    rows, cols = np.meshgrid(np.arange(sky45.height), np.arange(sky45.width), indexing="ij")
    directions = sky45.direction_of_texel(rows, cols)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-12)
    back_rows, back_cols = sky45.texel_of_direction(directions)
    np.testing.assert_array_equal(back_rows, rows)
    np.testing.assert_array_equal(back_cols, cols)
    # Same parameterisation as the rest of the library (docs/conventions.md).
    np.testing.assert_allclose(directions, envmap_directions(sky45.height), atol=1e-12)
    rng = np.random.default_rng(0)
    random = rng.normal(size=(500, 3))
    ours = sky45.texel_of_direction(random)
    theirs = direction_to_texel(random, sky45.height)
    np.testing.assert_array_equal(ours[0], theirs[0])
    np.testing.assert_array_equal(ours[1], theirs[1])
    # Row 0 at the zenith, azimuth counter-clockwise from +X: +Y is a quarter of the way round.
    assert [int(i) for i in sky45.texel_of_direction([0.0, 0.0, 1.0])] == [0, 0]
    assert int(sky45.texel_of_direction([0.0, 1.0, 1e-3])[1]) == sky45.width // 4


def test_sun_aureole_is_at_the_sun(sky45):
    # Above 20° of elevation (lower, the horizon below the sun is brighter than this clear aureole).
    upper = luminance(sky45.radiance[:24])
    brightest = np.unravel_index(np.argmax(upper), upper.shape)
    direction = sky45.direction_of_texel(*brightest)
    assert math.degrees(math.acos(np.clip(direction @ sky45.sun_direction, -1, 1))) < 3.0


# ------------------------------------------------------------------------------------------------
# Mitsuba
# ------------------------------------------------------------------------------------------------
def radiancemeter(mi, direction):
    return {"type": "radiancemeter", "origin": [0.0, 0.0, 0.0], "direction": [float(v) for v in direction],
            "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": 1}}


def narrow_camera(mi, direction):
    up = [0.0, 0.0, 1.0] if abs(direction[2]) < 0.9 else [1.0, 0.0, 0.0]
    return {"type": "perspective", "fov": 0.05,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[float(v) for v in direction], up=up),
            "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": 16, "seed": 0}}


def render(mi, sensor, emitters):
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2}, "sensor": sensor, **emitters})
    return np.array(mi.render(scene), dtype=np.float64).reshape(-1, 3).mean(axis=0)


def bilinear(image, rows, cols):
    """The map at continuous texel coordinates (centres at integers), wrapping in azimuth."""
    height, width, _ = image.shape
    r0 = int(np.floor(rows))
    c0 = int(np.floor(cols))
    wr, wc = rows - r0, cols - c0
    r0, r1 = min(max(r0, 0), height - 1), min(max(r0 + 1, 0), height - 1)
    c0, c1 = c0 % width, (c0 + 1) % width
    top = (1 - wc) * image[r0, c0] + wc * image[r0, c1]
    bottom = (1 - wc) * image[r1, c0] + wc * image[r1, c1]
    return (1 - wr) * top + wr * bottom


def test_mitsuba_envmap_renders_the_map(mi, sky45, tmp_path):
    emitters = envmap_emitter(sky45, tmp_path)
    assert len(list(tmp_path.glob("*.exr"))) == 1
    rotation = np.array(MITSUBA_ENVMAP_TO_WORLD)[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    sky_only = {"sky": emitters["sky"]}
    # Texel centres: near the zenith, around the sky (wrap-around columns included), by the sun,
    # just above and below the horizon, at the nadir.
    sun_row, sun_col = sky45.texel_of_direction(sky45.sun_direction)
    texels = [(0, 0), (0, 77), (5, 127), (12, 0), (20, 64), (sun_row, sun_col), (31, 3), (31, 100), (32, 50), (63, 9)]
    for row, col in texels:
        direction = sky45.direction_of_texel(row, col)
        rendered = render(mi, radiancemeter(mi, direction), sky_only)
        np.testing.assert_allclose(rendered, sky45.radiance[row, col], rtol=MITSUBA_RTOL, err_msg=f"texel {row, col}")
    # A small perspective camera between texel centres sees the map's bilinear interpolation.
    for row, col in [(3.3, 10.6), (17.5, 127.5), (25.8, 40.2), (45.2, 90.9)]:
        direction = sky45.direction_of_texel(row, col)
        rendered = render(mi, narrow_camera(mi, direction), sky_only)
        np.testing.assert_allclose(rendered, bilinear(sky45.radiance, row, col), rtol=MITSUBA_RTOL,
                                   err_msg=f"texel {row, col}")


def test_mitsuba_directional_sun_lights_a_white_plate_with_sun_radiance(mi, sky45, tmp_path):
    emitters = envmap_emitter(sky45, tmp_path)
    sun = sky45.sun_direction
    up = [0.0, 0.0, 1.0]
    plate = {"type": "rectangle",
             "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=sun.tolist(), up=up),
             "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}
    camera = {"type": "perspective", "fov": 5.0,
              "to_world": mi.ScalarTransform4f().look_at(origin=(5.0 * sun).tolist(), target=[0, 0, 0], up=up),
              "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
              "sampler": {"type": "independent", "sample_count": 4, "seed": 0}}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"}, "sensor": camera, "plate": plate,
                          "sun": emitters["sun"]})
    image = np.array(mi.render(scene), dtype=np.float64)[..., :3].reshape(-1, 3)
    np.testing.assert_allclose(image.mean(axis=0), sky45.sun_radiance, rtol=MITSUBA_RTOL)


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "sun",
    [[0.0, 1.0, -0.1], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 0.0, 0.0],
     [0.0, 1.0], [[0.0, 0.0, 1.0]], "up"],
)
def test_bad_sun_direction(sun):
    with pytest.raises(ValueError, match="sun_direction"):
        clear_sky(sun, width=8)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("ground_radius", -1.0),
        ("top_radius", 6_000_000.0),
        ("observer_altitude", -5.0),
        ("observer_altitude", 70_000.0),
        ("rayleigh_scattering", -1e-6),
        ("rayleigh_scale_height", 0.0),
        ("mie_scattering", np.nan),
        ("mie_albedo", 1.5),
        ("mie_g", 1.0),
        ("mie_phase", "rayleigh"),
        ("aerosol_scale", -1.0),
        ("angstrom_exponent", np.inf),
        ("ozone_column", -300.0),
        ("ozone_width", 0.0),
        ("ground_albedo", 1.2),
        ("sun_temperature", 0.0),
        ("solar_constant", "1361"),
        ("sun_angular_radius", 0.5),
        ("wavelength_min", 300.0),
        ("wavelength_max", 900.0),
        ("n_wavelengths", 2),
        ("n_wavelengths", 16.0),
        ("multiple_scattering", 1),
        ("view_steps", 1),
        ("transmittance_lut_shape", (64,)),
        ("ms_lut_shape", (32, 1)),
        ("ms_directions", [12, 8]),
        ("ms_steps", 0),
    ],
)
def test_bad_config_field(field, value):
    with pytest.raises(ValueError, match=field):
        AtmosphereConfig(**{field: value})


@pytest.mark.parametrize("width", [0, 6, 10, 64.0, True])
def test_bad_width(width):
    with pytest.raises(ValueError, match="width"):
        clear_sky([0.0, 0.0, 1.0], width=width)


@pytest.mark.parametrize("scale", [0.0, -1.0, np.nan, np.inf])
def test_bad_scale(scale):
    with pytest.raises(ValueError, match="scale"):
        clear_sky([0.0, 0.0, 1.0], width=8, scale=scale)
