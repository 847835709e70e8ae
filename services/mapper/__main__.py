from eqa.service import main
from services.mapper.service import MapperService

raise SystemExit(main(MapperService))
