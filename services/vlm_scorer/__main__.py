from eqa.service import main
from services.vlm_scorer.service import ScorerService

raise SystemExit(main(ScorerService))
