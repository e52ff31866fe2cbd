"""The short glossary at the foot of a report: the terms the page uses, each in a sentence or two. Only the terms
that appear on the page are listed."""

from __future__ import annotations

import html
import re

TERMS = {
    "PSNR": "Peak signal-to-noise ratio, in dB: 10 log10(1 / mean squared error) of two images with values in "
    "[0, 1]. Higher is better; +1 dB is about 21 % less squared error.",
    "SSIM": "Structural similarity (Wang et al. 2004): agreement of local means, contrasts and structure, 0 to 1. "
    "Higher is better.",
    "LPIPS": "Learned perceptual image patch similarity: the distance of two images in the features of a network "
    "trained to match human judgements (AlexNet, v0.1). Lower is better; n/a where its weights are not on the "
    "machine.",
    "held-out": "Not used in training: held-out lights relight the asset under light it never saw; held-out "
    "photos are views it never trained on.",
    "Full": "The method: per-view 2D material maps lifted onto the Gaussians and fused by the Neural Merger (a "
    "softmax over the views), refined with the 2D-map loss and the photometric loss while it learns the light.",
    "Without Softmax": "Full with the Neural Merger's softmax taken out: its weights over the views are "
    "unconstrained (the paper's supplementary ablation).",
    "Supervised": "Free per-Gaussian materials trained on the 2D maps alone, no photometric loss (the paper's "
    "Table 2).",
    "Proj. Average": "The mean of the 2D maps projected onto each Gaussian, with no training (the paper's Table 2).",
    "R3DGS-like": "The no-prior baseline: materials optimised per Gaussian from a uniform grey with the photometric "
    "loss and a learnt light, without any 2D maps, as Relightable 3D Gaussians (R3DGS, Gao et al. 2024) does; "
    "the paper's extended R3DGS column.",
    "Photos only": "What a run without 2D maps makes by default: the no-prior baseline's free per-Gaussian materials, "
    "but starting as a dielectric and pulled towards one (refine.metallic_prior_start and metallic_prior_weight), so "
    "a Gaussian turns metal only where the photos demand it. Not one of the paper's variants.",
    "2D predictions": "The per-view material maps of the 2D model for the test views, scored directly: what the "
    "method starts from and should improve on.",
    "split-sum": "The real-time approximation of image-based lighting (Karis 2013) the asset is shaded with: the "
    "light prefiltered per roughness times a pre-integrated BRDF term, instead of tracing rays.",
    "ground truth": "Mitsuba 3's path-traced render of the true object (or its true material maps).",
    "object mask": "The true silhouette: prediction and truth are both composited with it, so only the object counts "
    "(the paper's convention).",
    "object + silhouette (union)": "Each image composited with its own silhouette and scored over the union of the "
    "two, so that a missing or extra silhouette costs; not comparable with the object-mask rows.",
    "scale-aligned": "The prediction multiplied per channel by the median ratio truth / prediction before scoring "
    "(NeRFactor/TensoIR convention), which forgives a global brightness error.",
    "∞*": "Metallic PSNR is infinite where the true and predicted metallic maps are both all zero; such objects are "
    "counted apart and left out of the mean after the slash.",
    "lat-long": "An environment light stored as an image over longitude (across) and latitude (down), up at the "
    "top row.",
    "gradient energy": "The sum of squared differences between neighbouring pixels inside the object mask: how much "
    "fine detail an image holds. The asset's as a share of the photo's: below 1, softer than the photo.",
    "3DGS": "3D Gaussian Splatting, the geometry the asset is built on; its own view-dependent colours are the "
    "'radiance' render.",
}


def glossary_html(page_text: str) -> str:
    """A definition list of the TERMS found in `page_text` (the page so far), in TERMS' order; empty when none."""
    found = [term for term in TERMS if re.search(rf"(?<!\w){re.escape(term)}(?!\w)", page_text)]
    if not found:
        return ""
    items = "".join(f"<dt>{html.escape(term)}</dt><dd>{html.escape(TERMS[term])}</dd>" for term in found)
    return f'<h2 id="glossary">Glossary</h2><dl class="glossary">{items}</dl>'
