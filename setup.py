"""The build's one step beyond pyproject.toml: the documentation in docs/ ships inside the package, as
pomil/docs/*.md (``pomil docs`` reads it), from the one copy that the repository keeps."""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithDocs(build_py):
    def run(self) -> None:
        super().run()
        docs = Path(__file__).resolve().parent / "docs"
        target = Path(self.build_lib) / "pomil" / "docs"
        target.mkdir(parents=True, exist_ok=True)
        for page in sorted(docs.glob("*.md")):
            self.copy_file(str(page), str(target / page.name))


setup(cmdclass={"build_py": BuildWithDocs})
