"""TEST-ONLY stand-in for ``slicer.i18n`` (no translation); see ../README.md."""


def tr(text: str) -> str:
    return text


def translate(context: str, text: str) -> str:
    return text
