if (strstrt(GPVAL_TERMINALS, 'pngcairo') > 0) {
  set terminal pngcairo size 800,450
} else {
  set terminal png size 800,450
}
set output 'ms_per_step.png'
set title 'springblend: ms per frame (newton, each frame solved alone)'
set xlabel 'frame (alpha = frame / (steps - 1))'
set ylabel 'ms (log scale)'
set logscale y
set grid
set key outside right noenhanced
set xtics 1
plot 'ms_per_step.dat' index 0 using 1:2 with linespoints title 'cylinder', \
     'ms_per_step.dat' index 1 using 1:2 with linespoints title 'cube', \
     'ms_per_step.dat' index 2 using 1:2 with linespoints title 'cheburashka', \
     'ms_per_step.dat' index 3 using 1:2 with linespoints title 'face', \
     'ms_per_step.dat' index 4 using 1:2 with linespoints title 'face-mix', \
     'ms_per_step.dat' index 5 using 1:2 with linespoints title 'horse', \
     'ms_per_step.dat' index 6 using 1:2 with linespoints title 'cat'
