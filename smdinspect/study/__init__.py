"""The texture-variation study, and the operator choice it feeds.

:func:`run_texture_study` renders scenes of known shape with textures swept over
contrast, dominant frequency and kind at several sensor-noise levels, reconstructs each
with every focus operator and two peak fits, and writes tables, figures and a summary
(:func:`write_study`). :func:`choose_operator` measures a stack's texture
(:func:`stack_features`) and picks the operator the study's table (shipped as
``operator_table.json``; :func:`load_operator_table`) scores best there — what
``smdinspect reconstruct --operator auto`` uses.
"""

from ._auto import (
    TABLE_PATH,
    OperatorChoice,
    OperatorTable,
    choose_for_features,
    choose_operator,
    load_operator_table,
)
from ._features import TextureFeatures, stack_features, texture_features
from ._report import analyse_study, build_operator_table, summary_text, write_study
from ._texture import (
    METRICS,
    StudyCell,
    TextureStudy,
    TextureStudyConfig,
    render_cell,
    run_cell,
    run_texture_study,
    time_operators,
)

__all__ = [
    "METRICS",
    "OperatorChoice",
    "OperatorTable",
    "StudyCell",
    "TABLE_PATH",
    "TextureFeatures",
    "TextureStudy",
    "TextureStudyConfig",
    "analyse_study",
    "build_operator_table",
    "choose_for_features",
    "choose_operator",
    "load_operator_table",
    "render_cell",
    "run_cell",
    "run_texture_study",
    "stack_features",
    "summary_text",
    "texture_features",
    "time_operators",
    "write_study",
]
