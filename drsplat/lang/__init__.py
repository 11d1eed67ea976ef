"""The language field of a registered scene: storage backends, look-up-table scoring, PLY encoding.

Backends (`LanguageField.kind`):
- `exact`: features [N, D] stored as float16.
- `pq`: faiss product quantiser (`IndexPQ`), M sub-vectors x 8 bits, codes [N, M] uint8.
- `ivfpq`: faiss `IndexIVFPQ` (the official Dr. Splat codebook): a coarse list id per Gaussian plus
  a residual PQ code, reconstruction r = c[list] + Σ_m C[m, code_m].

Every backend scores a unit query q against Gaussian i by the cosine q·r_i / |r_i|, where r_i is
the stored (or reconstructed) feature and |r_i| is computed once. PQ backends never decode the
features to answer a query: a [M, 256] table of sub-vector inner products is gathered and summed
over the codes (`lut_scores` on the [N, M] codes; `lut_scores_blocked` on a blocked copy with
AVX-512 table look-ups, float32 tables or, optionally, 8-bit tables), see docs/index.md.

The registered PLY carries the field in extra vertex properties and a header comment
(docs/ARCHITECTURE.md, "The registered PLY"); the codebook file sits next to the PLY.
"""

from drsplat.lang.codebook import PQ_BITS, PQ_KSUB, Codebook, codebook_from_index, has_direction, load_codebook, train_codebook, undirected_rows_problem, unit_rows, unit_rows64
from drsplat.lang.backends import BACKENDS, KINDS, ExactStorage, PQStorage
from drsplat.lang.field import LanguageField, build_field
from drsplat.lang.lut import (
    Q8_BLOCK,
    blocked_codes,
    f32_sums,
    half_scores,
    inverse_norms,
    lut_scores,
    lut_scores_blocked,
    lut_scores_q8_reference,
    lut_scores_reference,
    q8_sums,
    quantize_luts,
    simd_available,
)
from drsplat.lang.plyformat import (
    COMMENT_PREFIX,
    EXPORT_FORMAT_HELP,
    EXPORT_FORMATS,
    META_PROPERTY,
    REGISTERED_IS_PLY,
    attach_field,
    codebook_name_for,
    codebook_path_for,
    decode_meta_column,
    encode_meta_column,
    encode_meta_columns,
    is_meta_column,
    export_kind,
    export_problem,
    other_data_name,
    export_scene,
    field_comment,
    field_extras,
    field_metadata,
    header_text_problem,
    is_lang_property,
    parse_field_comment,
    read_field,
    standard_scene,
    strip_field,
    written_codebook_path,
)

__all__ = [
    "BACKENDS", "COMMENT_PREFIX", "EXPORT_FORMATS", "EXPORT_FORMAT_HELP", "META_PROPERTY", "REGISTERED_IS_PLY", "decode_meta_column", "encode_meta_column", "encode_meta_columns", "is_meta_column", "export_kind", "export_problem", "export_scene", "other_data_name", "field_metadata", "standard_scene", "ExactStorage", "KINDS", "PQStorage", "PQ_BITS", "PQ_KSUB", "Q8_BLOCK", "Codebook", "LanguageField", "attach_field",
    "blocked_codes", "build_field", "codebook_from_index", "codebook_name_for", "codebook_path_for", "f32_sums",
    "field_comment", "field_extras", "half_scores", "header_text_problem", "has_direction", "inverse_norms", "is_lang_property", "load_codebook",
    "lut_scores", "lut_scores_blocked", "lut_scores_q8_reference", "lut_scores_reference", "parse_field_comment",
    "q8_sums", "quantize_luts", "read_field", "simd_available", "strip_field", "train_codebook", "undirected_rows_problem", "unit_rows", "unit_rows64",
    "written_codebook_path",
]
