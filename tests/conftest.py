import sys
from pathlib import Path

# Make the shared random-input helpers importable from every test module.
sys.path.insert(0, str(Path(__file__).parent))
