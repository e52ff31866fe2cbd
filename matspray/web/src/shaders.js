// `matspray relight`'s image as GLSL, in three passes, as relight renders it: materials and normals blended into a
// G-buffer, then shaded per pixel. Software WebGL (SwiftShader) spends its time per fragment and per render target:
// 1. PROJECT: one fragment per Gaussian projects it (its footprint on the screen); the splat pass only reads that.
// 2. SPLAT: the Gaussians back to front, premultiplied "over", into three float targets (base colour; the normal
//    turned to face the eye; roughness and metallic), each with the coverage in its alpha, which "over" blends by:
//    the same sums as `render.raster`'s front-to-back blending. EWA footprints with 0.3 px^2 added, alphas clamped
//    to 0.999 and dropped below 1/255 (more while the view moves), drawn as rectangles along the axes of the ellipse
//    where alpha reaches that, or, for small footprints, as one triangle around that ellipse (octagons, 17 % fewer
//    fragments, were slower: SwiftShader pays per triangle and for the 2 x 2 pixel blocks along each thin
//    triangle's edges).
// 3. SHADE: each blended pixel's materials divided by its coverage, shaded by split-sum image-based lighting
//    (`render.shade.deferred.shade_gbuffer`) with the view direction through the pixel's centre, composited over the
//    background and encoded to sRGB, clipped, as `relight` writes its PNGs. While the view moves, the splats are
//    blended and shaded at a fraction of the canvas's size and ENLARGE fills a block of the canvas with each shaded
//    pixel. A new light or exposure runs this pass alone.

const FETCH = /* glsl */ `
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D tCentre;   // mean xyz, opacity
uniform sampler2D tRotation; // unit quaternion w x y z
uniform sampler2D tScale;    // scales xyz, roughness
uniform sampler2D tBase;     // linear base colour rgb, metallic
uniform sampler2D tNormal;   // unit normal xyz
uniform vec3 eye;
`;

const VIEW = /* glsl */ `
uniform int texWidth;
uniform mat3 viewRotation;
uniform vec3 viewTranslation;
uniform vec4 intrinsics;     // fx fy cx cy
uniform vec2 size;           // width height in pixels
uniform float cutoff;        // the alpha below which a Gaussian blends nothing (CUTOFF in main.js)
`;

// PROJECT: each Gaussian's footprint, once (the splat pass's vertices only read it): its centre and major axis in
// gl_FragCoord's frame (rows from the bottom), the half sides of the rectangle around the ellipse where alpha falls
// to the cutoff (0 when it is not drawn), and those half sides in the ellipse's own units p, where
// alpha = opacity exp(-d^T conic d / 2) = opacity exp2(-|p|^2), p = (d.major, d.minor) / sqrt(2 ln 2 (l1, l2))
// for the footprint's eigenvalues l1 >= l2 and d the pixel's offset from the centre: p is linear in the pixel, so
// the splat pass interpolates it from the corners and its fragments only square it (docs/dev/web.md)
export const PROJECT_FRAGMENT = /* glsl */ `${FETCH}${VIEW}
layout(location = 0) out vec4 outCentreAxis;  // centre xy, major axis xy
layout(location = 1) out vec4 outExtent;      // half sides along the axes: in pixels, in p's units

void main() {
  outCentreAxis = vec4(0.0);
  outExtent = vec4(0.0);
  ivec2 uv = ivec2(gl_FragCoord.xy);  // this Gaussian's texel
  vec4 centre = texelFetch(tCentre, uv, 0);
  vec3 t = viewRotation * centre.xyz + viewTranslation;
  float opacity = centre.w;
  if (t.z <= 0.01 || opacity < cutoff) return;
  vec4 q = texelFetch(tRotation, uv, 0);
  vec4 sr = texelFetch(tScale, uv, 0);
  float w = q.x, x = q.y, y = q.z, z = q.w;
  mat3 R = mat3(  // columns
    1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
    2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
    2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
  mat3 M = viewRotation * R * mat3(sr.x, 0.0, 0.0, 0.0, sr.y, 0.0, 0.0, 0.0, sr.z);
  mat3 sigma = M * transpose(M);  // camera-space covariance
  float fx = intrinsics.x, fy = intrinsics.y, cx = intrinsics.z, cy = intrinsics.w;
  float px = t.x / t.z, py = t.y / t.z;
  float xc = clamp(px, -1.3 * cx / fx, 1.3 * (size.x - cx) / fx);
  float yc = clamp(py, -1.3 * cy / fy, 1.3 * (size.y - cy) / fy);
  vec3 a = vec3(fx / t.z, 0.0, -fx * xc / t.z);
  vec3 b = vec3(0.0, fy / t.z, -fy * yc / t.z);
  float cxx = dot(a, sigma * a) + 0.3;
  float cxy = dot(a, sigma * b);
  float cyy = dot(b, sigma * b) + 0.3;
  float det = cxx * cyy - cxy * cxy;
  if (det <= 0.0) return;
  float mid = 0.5 * (cxx + cyy);
  float root = sqrt(max(mid * mid - det, 0.0));
  float reach = 2.0 * log(opacity / cutoff);
  vec2 axis = abs(cxy) > 1e-12 ? normalize(vec2(mid + root - cyy, cxy)) : (cxx >= cyy ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 eigen = vec2(mid + root, det / (mid + root));
  vec2 halfSide = sqrt(reach * eigen) + 0.5;
  // in gl_FragCoord's frame, whose rows run up where the camera's run down: the axis's y changes sign
  outCentreAxis = vec4(fx * px + cx, size.y - (fy * py + cy), axis.x, -axis.y);
  outExtent = vec4(halfSide, halfSide * inversesqrt(2.0 * 0.6931471805599453 * eigen));
}`;

// four vertices a Gaussian around its rectangle, or three around its ellipse's circumscribed triangle (the unit
// circle's equilateral one, stretched as the ellipse: 30 % more area, one primitive instead of two): SwiftShader's
// cost per triangle outweighs the area for small footprints (TRIANGLE_FOOTPRINT in main.js)
export function splatVertex(corners) {
  return /* glsl */ `${FETCH}
#define CORNERS ${corners}
uniform sampler2D tOrder;    // the Gaussians' indices, back to front (one float each)
uniform sampler2D tCentreAxis;  // the PROJECT pass's
uniform sampler2D tExtent;
uniform int texWidth;
uniform vec2 size;           // width height in pixels
out vec2 vLocal;             // p (PROJECT_FRAGMENT): alpha = opacity exp2(-|p|^2)
flat out vec4 vBase;         // base colour, opacity
flat out vec4 vNormal;       // unit normal facing the eye, roughness
flat out float vMetallic;

void main() {
  // four vertices a Gaussian, drawn without instancing (SwiftShader runs each instance as a draw of its own)
  int slot = gl_VertexID / CORNERS;
  int corner = gl_VertexID % CORNERS;
#if CORNERS == 3
  vec2 position = corner == 0 ? vec2(0.0, 2.0) : vec2(corner == 1 ? -1.7320508 : 1.7320508, -1.0);
#else
  vec2 position = vec2(corner == 1 || corner == 2 ? 1.0 : -1.0, corner >= 2 ? 1.0 : -1.0);
#endif
  int i = int(texelFetch(tOrder, ivec2(slot % texWidth, slot / texWidth), 0).r);
  ivec2 uv = ivec2(i % texWidth, i / texWidth);
  vec4 extent = texelFetch(tExtent, uv, 0);
  if (extent.x <= 0.0) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  vec4 centreAxis = texelFetch(tCentreAxis, uv, 0);
  vec2 axis = centreAxis.zw;
  vec2 minor = vec2(-axis.y, axis.x);
  // on the 1/16 pixel grid that rasterisers snap vertices to (GLES asks at least 4 subpixel bits), so that p,
  // interpolated from the corners where they are drawn, is p at each pixel (unsnapped, it strays by up to 5 %)
  vec2 pixel = round(16.0 * (centreAxis.xy + position.x * extent.x * axis + position.y * extent.y * minor)) / 16.0;
  gl_Position = vec4(pixel / size * 2.0 - 1.0, 0.0, 1.0);
  vec2 d = pixel - centreAxis.xy;
  vLocal = vec2(dot(d, axis), dot(d, minor)) * extent.zw / extent.xy;
  vec4 centre = texelFetch(tCentre, uv, 0);
  vec4 base = texelFetch(tBase, uv, 0);
  vec3 n = texelFetch(tNormal, uv, 0).xyz;
  if (dot(n, eye - centre.xyz) < 0.0) n = -n;  // faces the eye before blending (render.raster.gbuffer.orient_normals)
  // the opacity clamped as render.raster clamps alpha (an opacity of 1 gives 0.999 exp2(-|p|^2) where it gave
  // min(0.999, exp2(-|p|^2)): 0.001 apart at most)
  vBase = vec4(base.rgb, min(centre.w, 0.999));
  vNormal = vec4(n, texelFetch(tScale, uv, 0).w);
  vMetallic = base.w;
}`;
}

export const SPLAT_FRAGMENT = /* glsl */ `
precision highp float;
in vec2 vLocal;
flat in vec4 vBase;
flat in vec4 vNormal;
flat in float vMetallic;
uniform float cutoff;
layout(location = 0) out vec4 outBase;      // base colour x alpha, alpha
layout(location = 1) out vec4 outNormal;    // normal x alpha, alpha
layout(location = 2) out vec4 outMaterial;  // roughness x alpha, metallic x alpha, 0, alpha

void main() {
  float alpha = vBase.a * exp2(-dot(vLocal, vLocal));
  alpha = alpha < cutoff ? 0.0 : alpha;  // a select, not a discard: cheaper in a SIMD rasteriser
  outBase = vec4(vBase.rgb * alpha, alpha);
  outNormal = vec4(vNormal.xyz * alpha, alpha);
  outMaterial = vec4(vec2(vNormal.w, vMetallic) * alpha, 0.0, alpha);
}`;

export const SCREEN_VERTEX = /* glsl */ `
in vec3 position;
void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }`;

// while the view moves: the frame shaded at the blended size, each of its pixels filling shrink x shrink of the canvas
export const ENLARGE_FRAGMENT = /* glsl */ `
precision highp float;
precision highp int;
uniform sampler2D tShaded;
uniform int shrink;
out vec4 colour;
void main() { colour = texelFetch(tShaded, ivec2(gl_FragCoord.xy) / shrink, 0); }`;

export function shadeFragment(levelCount) {
  return /* glsl */ `
precision highp float;
precision highp int;
precision highp sampler2D;
#define LEVELS ${levelCount}
uniform sampler2D tBlendedBase;      // the SPLAT pass's three targets
uniform sampler2D tBlendedNormal;
uniform sampler2D tBlendedMaterial;
uniform vec2 size;           // the blended targets' width height
uniform vec4 intrinsics;     // fx fy cx cy in the blended targets' pixels
uniform mat3 viewRotation;   // world to camera
uniform vec3 background;     // linear
uniform sampler2D tLut;      // split-sum table: rows n.v, columns roughness, (A, B)
uniform sampler2D tLight;    // the padded maps, one above another
uniform vec3 levelPlace[LEVELS + 1];  // first row, rows, columns of each specular level, then the irradiance
uniform float levelRoughness[LEVELS];
uniform float exposure;      // a factor on the radiance
out vec4 colour;

vec3 bilinear(vec3 place, vec2 p) {  // texel coordinates, clamped at the border (grid_sample's border padding)
  p = clamp(p, vec2(0.0), vec2(place.z - 1.0, place.y - 1.0));
  vec2 f = floor(p);
  vec2 t = p - f;
  ivec2 i0 = ivec2(f);
  ivec2 i1 = min(i0 + 1, ivec2(int(place.z) - 1, int(place.y) - 1));
  int row = int(place.x);
  vec3 a = texelFetch(tLight, ivec2(i0.x, row + i0.y), 0).rgb;
  vec3 b = texelFetch(tLight, ivec2(i1.x, row + i0.y), 0).rgb;
  vec3 c = texelFetch(tLight, ivec2(i0.x, row + i1.y), 0).rgb;
  vec3 d = texelFetch(tLight, ivec2(i1.x, row + i1.y), 0).rgb;
  return mix(mix(a, b, t.x), mix(c, d, t.x), t.y);
}

vec3 lookup(vec3 place, vec3 dir) {  // envmap.latlong_grids on a padded map
  float rho = length(dir.xy);
  float phi = rho < 1e-12 ? 0.0 : atan(dir.y, -dir.x);
  float theta = atan(rho, dir.z);
  float width = place.z - 2.0;
  float x = phi * width / (3.14159265358979 * (width + 1.0));
  return bilinear(place, vec2((x + 1.0) * 0.5 * (place.z - 1.0), theta / 3.14159265358979 * (place.y - 1.0)));
}

vec2 lut(float nv, float r) {  // align_corners=False, border
  vec2 p = clamp(vec2(r, nv) * 32.0 - 0.5, vec2(0.0), vec2(31.0));
  vec2 f = floor(p);
  vec2 t = p - f;
  ivec2 i0 = ivec2(f);
  ivec2 i1 = min(i0 + 1, ivec2(31));
  vec2 a = texelFetch(tLut, ivec2(i0.x, i0.y), 0).rg;
  vec2 b = texelFetch(tLut, ivec2(i1.x, i0.y), 0).rg;
  vec2 c = texelFetch(tLut, ivec2(i0.x, i1.y), 0).rg;
  vec2 d = texelFetch(tLut, ivec2(i1.x, i1.y), 0).rg;
  return mix(mix(a, b, t.x), mix(c, d, t.x), t.y);
}

void main() {
  ivec2 texel = ivec2(gl_FragCoord.xy);
  vec4 blendedBase = texelFetch(tBlendedBase, texel, 0);
  float coverage = blendedBase.a;
  vec3 rgb = vec3(0.0);
  if (coverage > 0.0) {  // the targets hold sums weighted by alpha (render.shade.deferred.GBuffer.from_accumulated)
    float cover = max(coverage, 1e-6);
    vec3 albedo = blendedBase.rgb / cover;
    vec4 material = texelFetch(tBlendedMaterial, texel, 0) / cover;
    float metallic = material.y;
    float r = clamp(material.x, 0.04, 1.0);
    vec3 n = texelFetch(tBlendedNormal, texel, 0).xyz;
    n = n / max(length(n), 1e-12);
    // the reversed camera ray through the blended pixel's centre (camera rows run down, gl_FragCoord's up)
    vec2 pixel = vec2(float(texel.x) + 0.5, size.y - float(texel.y) - 0.5);
    vec3 wo = -normalize(transpose(viewRotation) * vec3((pixel - intrinsics.zw) / intrinsics.xy, 1.0));
    float nv = dot(n, wo);
    if (nv < 0.0) { n = -n; nv = -nv; }  // faces the camera, as shade_unit turns it
    vec2 ab = lut(nv, r);
    vec3 f0 = 0.04 * (1.0 - metallic) + albedo * metallic;
    float a = r * r;
    float s = 1.0 - a;
    vec3 lobe = mix(n, reflect(-wo, n), pow(s, 1.5) + s * a);
    // linear between the two levels around r (envmap._level_weights)
    float rc = clamp(r, levelRoughness[0], levelRoughness[LEVELS - 1]);
    int low = 0;
    for (int i = 1; i < LEVELS - 1; i++) low += rc >= levelRoughness[i] ? 1 : 0;
    float t = (rc - levelRoughness[low]) / (levelRoughness[low + 1] - levelRoughness[low]);
    vec3 specular = (1.0 - t) * lookup(levelPlace[low], lobe) + t * lookup(levelPlace[low + 1], lobe);
    vec3 irradiance = lookup(levelPlace[LEVELS], n);
    rgb = irradiance * albedo * (1.0 - metallic) / 3.14159265358979 + specular * (f0 * ab.x + ab.y);
  }
  vec3 x = clamp(rgb * exposure * coverage + background * (1.0 - coverage), 0.0, 1.0);
  colour = vec4(mix(12.92 * x, 1.055 * pow(max(x, vec3(1e-12)), vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x)), 1.0);
}`;
}
