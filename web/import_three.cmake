# cmake -DIN=addon.js -DOUT=out.js -P import_three.cmake: the addon importing three.module.js from
# beside it instead of the bare name 'three'.
file(READ ${IN} text)
string(REPLACE "from 'three';" "from './three.module.js';" text "${text}")
string(REPLACE "from \"three\";" "from './three.module.js';" text "${text}")
if(text MATCHES "from ['\"]three['\"]")
  message(FATAL_ERROR "${IN} still imports 'three'")
endif()
file(WRITE ${OUT} "${text}")
