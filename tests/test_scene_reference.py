"""docs/scene_reference.md is generated from the schema and must match it."""
from pathlib import Path

from opera_taichi import scene as schema
from opera_taichi.scene import Scene, scene_reference_markdown

DOC = Path(__file__).resolve().parents[1] / "docs" / "scene_reference.md"


def test_committed_reference_is_up_to_date():
    assert DOC.read_text() == scene_reference_markdown(), \
        "regenerate: python -m opera_taichi.scene > docs/scene_reference.md"


def test_every_user_key_is_documented_with_a_description():
    page = scene_reference_markdown()

    models = [obj for obj in vars(schema).values()
              if isinstance(obj, type) and issubclass(obj, schema._Model) and obj is not schema._Model]
    assert Scene in models and len(models) >= 12
    for model in models:
        for key, field in model.model_fields.items():
            if key == "source":
                continue
            assert field.description, f"{model.__name__}.{key} has no description"
            assert f"| `{key}` |" in page, f"{model.__name__}.{key} missing from the reference"
